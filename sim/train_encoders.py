"""Train the two compact image-text encoders that ship with olsplat, on simulator renders.

They are stand-ins: models that know the simulator's world (its roofs, roads, lawns, trees,
cars), so that the whole pipeline runs on a fresh machine with no downloads. Users with
RemoteCLIP / GeoRSCLIP weights export those with ``olsplat export-clip`` instead.

Two designs, so that the paper's two-encoder fusion (λ2D) and its one-encoder ablations
have two genuinely different encoders to combine:
- ``olsplat-cnn64``: a small CNN on 64 px crops with tight context (box + 25 %, outside faded);
- ``olsplat-vit48``: a small ViT on 48 px crops with wide context (box + 60 %, lightly faded).
Each has its own whole-word text tower (mean of word embeddings, then an MLP).

Training: region crops of views of seeds >= TRAINING_SEED_BASE, labelled by their majority
ground-truth label; each crop is pulled towards all captions of its label and away from the
others (a cross-entropy over every caption, the target spread evenly over the label's
captions, classes weighted against their frequency); random flips, quarter turns and
brightness changes. Seeded: the same command gives the same models up to float rounding.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from olsplat_nodes.encoders import CropConfig
from olsplat_nodes.encoders.clip_model import Transformer
from olsplat_nodes.encoders.export import export_tower, write_manifest
from olsplat_nodes.encoders.tokenizer import WordTokenizer

from .labels import LABELS, QUERIES
from .region_samples import CAPTIONS, TRAINING_SEED_BASE, RegionSamples, collect

EMBED_DIM = 64
CONTEXT = 16
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)
ASSETS = Path(__file__).resolve().parents[1] / "olsplat_nodes" / "encoders" / "assets"


@dataclass(frozen=True)
class Design:
    name: str
    image_size: int
    crop: CropConfig
    kind: str  # "cnn" or "vit"


DESIGNS = (
    Design("olsplat-cnn64", 64, CropConfig(context=0.25, fade=0.7), "cnn"),
    Design("olsplat-vit48", 48, CropConfig(context=0.6, fade=0.4), "vit"),
)


class CnnImageTower(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        layers, channels = [], 3
        for width in (32, 64, 96, 128):
            layers += [nn.Conv2d(channels, width, 3, stride=2, padding=1), nn.BatchNorm2d(width), nn.ReLU()]
            channels = width
        self.features = nn.Sequential(*layers, nn.Conv2d(128, 128, 3, padding=1), nn.ReLU())
        self.head = nn.Linear(128, dim)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(pixels).mean(dim=(2, 3)))


class VitImageTower(nn.Module):
    def __init__(self, dim: int, size: int, patch: int = 8, width: int = 96, layers: int = 3):
        super().__init__()
        self.patchify = nn.Conv2d(3, width, patch, patch)
        self.cls = nn.Parameter(0.02 * torch.randn(width))
        self.position = nn.Parameter(0.02 * torch.randn((size // patch) ** 2 + 1, width))
        self.transformer = Transformer(width, layers, width // 32, "gelu")
        self.norm = nn.LayerNorm(width)
        self.head = nn.Linear(width, dim)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = self.patchify(pixels).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls.expand(x.shape[0], 1, -1), x], dim=1) + self.position
        return self.head(self.norm(self.transformer(x)[:, 0]))


class WordTextTower(nn.Module):
    def __init__(self, vocab_size: int, dim: int, width: int = 96):
        super().__init__()
        self.embedding = nn.Embedding(vocab_size, width, padding_idx=0)
        self.mlp = nn.Sequential(nn.Linear(width, 2 * width), nn.GELU(), nn.Linear(2 * width, dim))

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        mask = (tokens > 0).float().unsqueeze(-1)
        mean = (self.embedding(tokens) * mask).sum(1) / mask.sum(1).clamp(min=1.0)
        return self.mlp(mean)


def vocabulary(captions: dict[str, list[str]] | None = None) -> list[str]:
    """Every word of the training captions (``CAPTIONS`` by default; query texts are left out on purpose)."""
    probe = WordTokenizer.__new__(WordTokenizer)  # only its text splitting is used
    table = CAPTIONS if captions is None else captions
    return sorted({word for texts in table.values() for text in texts for word in probe.words(text)})


def _augment(batch: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Random quarter turns, flips and brightness: aerial crops have no 'up'."""
    turns = int(torch.randint(0, 4, (1,), generator=generator))
    batch = torch.rot90(batch, turns, dims=(2, 3))
    if torch.rand(1, generator=generator) < 0.5:
        batch = batch.flip(3)
    gain = 1.0 + 0.15 * (torch.rand(batch.shape[0], 1, 1, 1, generator=generator) * 2 - 1)
    return batch * gain


def train_design(design: Design, samples: RegionSamples, tokenizer: WordTokenizer, epochs: int, seed: int, log=print,
                 captions: dict[str, list[str]] | None = None, on_step=None):  # fmt: skip
    """(image tower, text tower) trained on ``samples`` (see the module docstring).

    ``captions``: label -> training texts (default ``CAPTIONS``); ``on_step(step, image_tower,
    text_tower)``: called after every optimizer step (1, 2, ...), towers in training mode, e.g. to
    keep checkpoints (``sim.train_pair``); it must not draw random numbers or change the towers.
    """
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    image_tower = CnnImageTower(EMBED_DIM) if design.kind == "cnn" else VitImageTower(EMBED_DIM, design.image_size)
    text_tower = WordTextTower(tokenizer.vocab_size, EMBED_DIM)
    table = CAPTIONS if captions is None else captions
    caption_rows = [(LABELS.index(label), text) for label, texts in table.items() for text in texts]
    caption_tokens = torch.from_numpy(tokenizer([text for _, text in caption_rows]))
    caption_label = torch.tensor([label for label, _ in caption_rows])
    target_table = (caption_label[None, :] == torch.arange(len(LABELS))[:, None]).float()
    target_table /= target_table.sum(1, keepdim=True).clamp(min=1.0)  # [labels, captions]
    counts = np.bincount(samples.labels, minlength=len(LABELS)).astype(np.float64)
    class_weight = torch.tensor(
        np.clip(counts.sum() / np.maximum(counts, 1) / len(LABELS), 0.2, 5.0), dtype=torch.float32
    )

    pixels = torch.from_numpy(samples.crops[design.name]).permute(0, 3, 1, 2).float() / 255.0
    pixels = (pixels - torch.tensor(MEAN)[:, None, None]) / torch.tensor(STD)[:, None, None]
    labels = torch.from_numpy(samples.labels)
    params = list(image_tower.parameters()) + list(text_tower.parameters())
    optimizer = torch.optim.AdamW(params, lr=2e-3, weight_decay=0.01)
    steps = epochs * int(np.ceil(len(labels) / 256))
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=2e-3, total_steps=steps)
    scale = 1 / 0.07
    start = time.perf_counter()
    for epoch in range(epochs):
        order = torch.randperm(len(labels), generator=generator)
        total, correct = 0.0, 0
        image_tower.train()
        for first in range(0, len(order), 256):
            index = order[first : first + 256]
            images = nn.functional.normalize(image_tower(_augment(pixels[index], generator)), dim=-1)
            texts = nn.functional.normalize(text_tower(caption_tokens), dim=-1)
            logits = scale * images @ texts.T
            loss_each = -(target_table[labels[index]] * logits.log_softmax(-1)).sum(-1)
            loss = (loss_each * class_weight[labels[index]]).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()
            if on_step is not None:
                on_step(schedule.last_epoch, image_tower, text_tower)
            total += float(loss.detach()) * len(index)
            predicted = caption_label[logits.argmax(-1)]
            correct += int((predicted == labels[index]).sum())
        log(f"{design.name} epoch {epoch + 1}/{epochs}: loss {total / len(labels):.3f}, "
            f"train accuracy {correct / len(labels):.3f} ({time.perf_counter() - start:.0f} s)")  # fmt: skip
    return image_tower.eval(), text_tower.eval()


def export_design(design: Design, image_tower, text_tower, vocab: list[str], out: Path, trained_on: str | None = None,
                  ) -> Path:  # fmt: skip
    folder = out / design.name
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps(vocab))
    tokenizer = WordTokenizer(folder / "vocab.json", CONTEXT)
    with torch.no_grad():
        export_tower(
            image_tower, torch.zeros(2, 3, design.image_size, design.image_size), folder / "image.onnx", "pixels"
        )
        export_tower(text_tower, torch.from_numpy(tokenizer(["a red roof", "a road"])), folder / "text.onnx", "tokens")
    write_manifest(
        folder, design.name, EMBED_DIM, design.image_size, CONTEXT, tokenizer.vocab_size, MEAN, STD, "vocab.json",
        "words", crop={"context": design.crop.context, "fade": design.crop.fade, "min_box_px": design.crop.min_box_px},
        trained_on=trained_on or "olsplat simulator renders, seeds >= 1000 (never the evaluation seeds)",
    )  # fmt: skip
    return folder


def train_all(out: Path = ASSETS, n_seeds: int = 10, views: int = 16, epochs: int = 8, log=print) -> list[Path]:
    torch.set_num_threads(max(1, torch.get_num_threads()))
    start = time.perf_counter()
    seeds = list(range(TRAINING_SEED_BASE, TRAINING_SEED_BASE + n_seeds))
    samples = collect(seeds, views, {d.name: (d.image_size, d.crop) for d in DESIGNS})
    log(f"{len(samples.labels)} region crops from {n_seeds} scenes x {views} views "
        f"in {time.perf_counter() - start:.0f} s; per label: "
        f"{dict(zip(LABELS, np.bincount(samples.labels, minlength=len(LABELS)).tolist(), strict=True))}")  # fmt: skip
    vocab = vocabulary()
    out.mkdir(parents=True, exist_ok=True)
    tmp_vocab = out / "_vocab.json"
    tmp_vocab.write_text(json.dumps(vocab))
    tokenizer = WordTokenizer(tmp_vocab, CONTEXT)
    tmp_vocab.unlink()
    folders = []
    for i, design in enumerate(DESIGNS):
        image_tower, text_tower = train_design(design, samples, tokenizer, epochs, seed=i, log=log)
        folders.append(export_design(design, image_tower, text_tower, vocab, out))
    unused = sorted({w for text, _, _ in QUERIES for w in tokenizer.words(text)} - set(vocab))
    log(f"query words the text towers never saw (map to a known singular or to <unknown>): {unused}")
    log(f"done in {time.perf_counter() - start:.0f} s -> {', '.join(map(str, folders))}")
    return folders
