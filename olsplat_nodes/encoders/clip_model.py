"""A CLIP ViT (image tower + text tower) in plain PyTorch that loads open_clip state dicts.

RemoteCLIP and GeoRSCLIP (RS5M) are released as open_clip checkpoints of the ``ViT-B-32``
(or larger) model. This module rebuilds that model from the checkpoint's own tensors, with
the same parameter names, so that ``load_state_dict`` takes the file as it is; open_clip and
torchvision are not needed (and cannot be installed here). Used only to export ONNX files:
at run time olsplat runs the ONNX files with onnxruntime.

Key layout (open_clip ``CLIP`` with a ``VisionTransformer``):
``visual.conv1.weight``, ``visual.class_embedding``, ``visual.positional_embedding``,
``visual.ln_pre.*``, ``visual.transformer.resblocks.{i}.{ln_1,attn,ln_2,mlp}.*``,
``visual.ln_post.*``, ``visual.proj``; ``token_embedding.weight``, ``positional_embedding``,
``transformer.resblocks.{i}.*``, ``ln_final.*``, ``text_projection``, ``logit_scale``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

Activation = Literal["gelu", "quick_gelu"]


@dataclass(frozen=True)
class ClipConfig:
    embed_dim: int
    image_size: int
    patch_size: int
    vision_width: int
    vision_layers: int
    context_length: int
    vocab_size: int
    text_width: int
    text_layers: int
    head_width: int = 64  # channels per attention head (CLIP's choice for every size)
    activation: Activation = "gelu"  # open_clip ViT-B-32: gelu; OpenAI weights: quick_gelu

    @staticmethod
    def from_state_dict(state: dict[str, torch.Tensor], activation: Activation = "gelu") -> ClipConfig:
        """Read the architecture off the tensors' shapes (raises KeyError naming a missing key)."""

        def layers(prefix: str) -> int:
            found = {int(m.group(1)) for k in state if (m := re.match(re.escape(prefix) + r"(\d+)\.", k))}
            return max(found) + 1 if found else 0

        patch = state["visual.conv1.weight"].shape[-1]
        grid = int(round(math.sqrt(state["visual.positional_embedding"].shape[0] - 1)))
        return ClipConfig(
            embed_dim=state["text_projection"].shape[1],
            image_size=patch * grid,
            patch_size=patch,
            vision_width=state["visual.conv1.weight"].shape[0],
            vision_layers=layers("visual.transformer.resblocks."),
            context_length=state["positional_embedding"].shape[0],
            vocab_size=state["token_embedding.weight"].shape[0],
            text_width=state["ln_final.weight"].shape[0],
            text_layers=layers("transformer.resblocks."),
            activation=activation,
        )


class QuickGELU(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class Attention(nn.Module):
    """Multi-head self-attention with nn.MultiheadAttention's parameter names (in_proj_*, out_proj)."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * width))
        self.out_proj = nn.Linear(width, width)
        nn.init.xavier_uniform_(self.in_proj_weight)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        batch, tokens, width = x.shape
        qkv = nn.functional.linear(x, self.in_proj_weight, self.in_proj_bias)
        q, k, v = qkv.reshape(batch, tokens, 3, self.heads, width // self.heads).permute(2, 0, 3, 1, 4)
        out = nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.out_proj(out.transpose(1, 2).reshape(batch, tokens, width))


class ResidualBlock(nn.Module):
    def __init__(self, width: int, heads: int, activation: Activation):
        super().__init__()
        self.ln_1 = nn.LayerNorm(width)
        self.attn = Attention(width, heads)
        self.ln_2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential()
        self.mlp.add_module("c_fc", nn.Linear(width, 4 * width))
        self.mlp.add_module("gelu", QuickGELU() if activation == "quick_gelu" else nn.GELU())
        self.mlp.add_module("c_proj", nn.Linear(4 * width, width))

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x), mask)
        return x + self.mlp(self.ln_2(x))


class Transformer(nn.Module):
    def __init__(self, width: int, layers: int, heads: int, activation: Activation):
        super().__init__()
        self.resblocks = nn.ModuleList([ResidualBlock(width, heads, activation) for _ in range(layers)])

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        for block in self.resblocks:
            x = block(x, mask)
        return x


class VisionTower(nn.Module):
    def __init__(self, c: ClipConfig):
        super().__init__()
        grid = c.image_size // c.patch_size
        scale = c.vision_width**-0.5
        self.conv1 = nn.Conv2d(3, c.vision_width, c.patch_size, c.patch_size, bias=False)
        self.class_embedding = nn.Parameter(scale * torch.randn(c.vision_width))
        self.positional_embedding = nn.Parameter(scale * torch.randn(grid * grid + 1, c.vision_width))
        self.ln_pre = nn.LayerNorm(c.vision_width)
        self.transformer = Transformer(c.vision_width, c.vision_layers, c.vision_width // c.head_width, c.activation)
        self.ln_post = nn.LayerNorm(c.vision_width)
        self.proj = nn.Parameter(scale * torch.randn(c.vision_width, c.embed_dim))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """[B, 3, S, S] normalised pixels -> [B, embed_dim] (not normalised)."""
        x = self.conv1(pixels).flatten(2).transpose(1, 2)  # [B, grid^2, width]
        cls = self.class_embedding.expand(x.shape[0], 1, -1)
        x = self.ln_pre(torch.cat([cls, x], dim=1) + self.positional_embedding)
        x = self.transformer(x)
        return self.ln_post(x[:, 0]) @ self.proj


class ClipModel(nn.Module):
    def __init__(self, c: ClipConfig):
        super().__init__()
        self.config = c
        self.visual = VisionTower(c)
        self.token_embedding = nn.Embedding(c.vocab_size, c.text_width)
        self.positional_embedding = nn.Parameter(0.01 * torch.randn(c.context_length, c.text_width))
        self.transformer = Transformer(c.text_width, c.text_layers, c.text_width // c.head_width, c.activation)
        self.ln_final = nn.LayerNorm(c.text_width)
        self.text_projection = nn.Parameter(c.text_width**-0.5 * torch.randn(c.text_width, c.embed_dim))
        self.logit_scale = nn.Parameter(torch.tensor(math.log(1 / 0.07)))
        causal = torch.full((c.context_length, c.context_length), float("-inf")).triu(1)
        self.register_buffer("attn_mask", causal, persistent=False)

    def encode_image(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.visual(pixels)

    def encode_text(self, tokens: torch.Tensor) -> torch.Tensor:
        """[T, context_length] int64 token ids -> [T, embed_dim]: the end-of-text token's feature.

        The end-of-text token has the largest id in CLIP's vocabulary, so argmax finds it.
        """
        x = self.token_embedding(tokens) + self.positional_embedding
        x = self.ln_final(self.transformer(x, self.attn_mask))
        eot = tokens.argmax(dim=-1)
        return x[torch.arange(x.shape[0]), eot] @ self.text_projection


def clean_state_dict(raw: dict) -> dict[str, torch.Tensor]:
    """Unwrap the containers checkpoints come in ({"state_dict": ...}, "module." prefixes)."""
    state = raw.get("state_dict", raw.get("model", raw)) if isinstance(raw, dict) else raw
    return {k.removeprefix("module."): v for k, v in state.items() if isinstance(v, torch.Tensor)}


def load_clip(path: str, activation: Activation = "gelu") -> ClipModel:
    """Load an open_clip CLIP checkpoint (a .pt/.bin state dict) into a ClipModel.

    Raises ValueError naming the file for missing, unexpected or mis-shaped keys.
    """
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        # torch's own text may advise loading with weights_only=False: never do that with a file of
        # unknown origin (it runs code); say what is wrong instead
        reason = "truncated or damaged" if isinstance(exc, (EOFError, RuntimeError)) else type(exc).__name__
        raise ValueError(
            f"{path}: not a readable PyTorch checkpoint of tensors ({reason}); olsplat loads tensors only, "
            "never pickled code"
        ) from None
    state = clean_state_dict(raw)
    try:
        config = ClipConfig.from_state_dict(state, activation)
    except KeyError as exc:
        raise ValueError(f"{path}: not an open_clip CLIP ViT checkpoint (no key {exc.args[0]!r})") from None
    model = ClipModel(config)
    state = {
        k: v for k, v in state.items() if k not in ("attn_mask", "input_resolution", "context_length", "vocab_size")
    }
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:
        raise ValueError(
            f"{path}: tensor shapes do not match a CLIP ViT ({str(exc).splitlines()[-1].strip()})"
        ) from None
    if missing or unexpected:
        raise ValueError(f"{path}: keys do not match a CLIP ViT (missing {missing[:4]}, unexpected {unexpected[:4]})")
    return model.eval()
