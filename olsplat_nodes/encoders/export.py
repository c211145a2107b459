"""``olsplat export-clip``: an open_clip checkpoint -> ONNX image and text towers + manifest.

The output folder is what ``OnnxEncoder`` loads:

    encoder.json   manifest: name, embedding size, crop size, pixel mean/std, context length,
                   vocabulary size and the file names below
    image.onnx     [B, 3, S, S] float32 normalised pixels -> [B, D] image embeddings
    text.onnx      [T, context_length] int64 token ids -> [T, D] text embeddings
    vocab.txt.gz   the BPE merges the text tower was trained with (copied)
"""

from __future__ import annotations

import json
import logging
import shutil
import warnings
from pathlib import Path

import torch

from .clip_model import Activation, ClipModel, load_clip
from .onnx_encoder import MANIFEST
from .tokenizer import ClipTokenizer

OPENAI_MEAN = (0.48145466, 0.4578275, 0.40821073)  # the pixel statistics CLIP models are trained with
OPENAI_STD = (0.26862954, 0.26130258, 0.27577711)


class _ImageTower(torch.nn.Module):
    def __init__(self, model: ClipModel):
        super().__init__()
        self.model = model

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.model.encode_image(pixels)


class _TextTower(_ImageTower):
    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return self.model.encode_text(tokens)


def export_tower(module: torch.nn.Module, example: torch.Tensor, path: Path, input_name: str) -> None:
    batch = torch.export.Dim("batch", min=1, max=4096)
    # the exporter logs a line per torchvision operator it cannot find; we need none of them
    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's progress chatter and deprecation notes
        torch.onnx.export(
            module, (example,), str(path), input_names=[input_name], output_names=["embeddings"],
            dynamic_shapes=({0: batch},), verbose=False, external_data=False,
        )  # fmt: skip


def export_model(
    model: ClipModel, vocab: str | Path, out: str | Path, name: str, mean=OPENAI_MEAN, std=OPENAI_STD
) -> Path:
    """Export a ClipModel (with its BPE vocabulary) to an ONNX encoder folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    c = model.config
    tokenizer = ClipTokenizer(vocab, context_length=c.context_length)
    if tokenizer.vocab_size != c.vocab_size:
        raise ValueError(
            f"{vocab}: {tokenizer.vocab_size} tokens, but the text tower embeds {c.vocab_size}: not its vocabulary"
        )
    model = model.eval()
    with torch.no_grad():
        export_tower(_ImageTower(model), torch.zeros(2, 3, c.image_size, c.image_size), out / "image.onnx", "pixels")
        export_tower(_TextTower(model), torch.as_tensor(tokenizer(["a photo", "a map"])), out / "text.onnx", "tokens")
    if str(vocab).endswith(".gz"):
        shutil.copyfile(vocab, out / "vocab.txt.gz")
    else:
        _gzip_copy(vocab, out / "vocab.txt.gz")
    write_manifest(
        out, name, c.embed_dim, c.image_size, c.context_length, c.vocab_size, mean, std, "vocab.txt.gz", "clip-bpe"
    )
    return out


def write_manifest(folder: Path, name: str, embed_dim: int, image_size: int, context_length: int, vocab_size: int,
                   mean, std, vocab: str, tokenizer: str, **extra) -> None:  # fmt: skip
    """The ``encoder.json`` that ``OnnxEncoder`` reads (``extra``: e.g. ``crop``, provenance)."""
    manifest = {
        "format": "olsplat-clip-onnx",
        "version": 1,
        "name": name,
        "embed_dim": embed_dim,
        "image_size": image_size,
        "context_length": context_length,
        "vocab_size": vocab_size,
        "mean": list(mean),
        "std": list(std),
        "image": "image.onnx",
        "text": "text.onnx",
        "vocab": vocab,
        "tokenizer": tokenizer,
        **extra,
    }
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=2))


def _gzip_copy(src, dst) -> None:
    """Gzip ``src`` to ``dst`` with no name or time in the header: the same vocabulary, the same bytes."""
    import gzip

    with open(src, "rb") as f, open(dst, "wb") as raw, gzip.GzipFile(filename="", fileobj=raw, mode="wb", mtime=0) as g:
        g.write(f.read())


def export_clip(
    checkpoint: str | Path, vocab: str | Path, out: str | Path, activation: Activation = "gelu", name: str | None = None
) -> Path:
    """Load an open_clip checkpoint and export it (see the module docstring)."""
    model = load_clip(str(checkpoint), activation)
    return export_model(model, vocab, out, name or Path(checkpoint).stem)
