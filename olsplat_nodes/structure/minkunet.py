"""MinkUNet (the SegContrast backbone) on ``sparse_conv``, loading MinkowskiEngine checkpoints.

Architecture: channels cs = [32, 32, 64, 128, 256, 256, 128, 96, 96] (times a ratio ``cr``), a
stem of two 3x3x3 convolutions, four down stages (2x2x2 stride-2 conv + two residual blocks),
four up stages (2x2x2 stride-2 transposed conv, concatenation with the skip, two residual
blocks); the output is cs[8] = 96 features per voxel, the paper's 3D structural feature.
Batch norm runs in inference mode (running statistics).

Expected checkpoint: a PyTorch file holding the model's state dict, either directly or under
"model", "model_state_dict" or "state_dict" (a "module." prefix from DataParallel is
stripped), with MinkowskiEngine's key names, e.g. ``stem.0.kernel`` [27, 4, 32],
``stem.1.bn.running_mean``, ``stage1.1.net.0.kernel``, ``up1.0.net.0.kernel`` [8, 256, 256].
SegContrast's pre-trained backbone is such a file (its input has 4 channels: here
[normalised x, y, z, opacity]). Keys or shapes that do not match are reported by name.
Loaded with ``weights_only=True``: a checkpoint cannot run code. The channel ratio ``cr``
(SegContrast's MinkUNet takes one; 1.0 = the sizes above) and the number of input channels are
read from ``stem.0.kernel``'s shape, so smaller networks of the same layout load too.

Input recipes (what the input channels mean), chosen by the checkpoint's optional "olsplat"
record: "xyz-opacity" (no record: SegContrast's xyz + intensity, here [x, y, z centred and
divided by their largest spread, opacity] on the world-axis voxel grid) or "height-opacity"
(checkpoints pre-trained by ``segcontrast.pretrain``: see ``segcontrast.ground_frame``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import SceneFormatError
from .ground_frame import ground_frame, voxelise
from .points import StructuralPoints
from .sparse_conv import SparseTensor, conv, conv_transpose

CHANNELS = (32, 32, 64, 128, 256, 256, 128, 96, 96)


class Conv(nn.Module):
    def __init__(self, c_in: int, c_out: int, size: int, stride: int = 1, transpose: bool = False):
        super().__init__()
        self.size, self.stride, self.transpose = size, stride, transpose
        self.kernel = nn.Parameter(torch.randn(size**3, c_in, c_out) / np.sqrt(size**3 * c_in))

    def forward(self, x: SparseTensor) -> SparseTensor:
        return (conv_transpose if self.transpose else conv)(x, self.kernel, self.size, self.stride)


class BatchNorm(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.bn = nn.BatchNorm1d(channels)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(self.bn(x.feats))


class ReLU(nn.Module):
    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(torch.relu(x.feats))


def _conv_bn_relu(c_in, c_out, size, stride, transpose=False):
    return nn.Sequential(Conv(c_in, c_out, size, stride, transpose), BatchNorm(c_out), ReLU())


class BasicBlock(nn.Module):  # "BasicConvolutionBlock" / "BasicDeconvolutionBlock"
    def __init__(self, c_in, c_out, transpose=False):
        super().__init__()
        self.net = _conv_bn_relu(c_in, c_out, 2, 2, transpose)

    def forward(self, x):
        return self.net(x)


class ResidualBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.net = nn.Sequential(
            Conv(c_in, c_out, 3), BatchNorm(c_out), ReLU(), Conv(c_out, c_out, 3), BatchNorm(c_out)
        )
        self.downsample = nn.Sequential() if c_in == c_out else nn.Sequential(Conv(c_in, c_out, 1), BatchNorm(c_out))

    def forward(self, x: SparseTensor) -> SparseTensor:
        skip = self.downsample(x) if len(self.downsample) else x
        return x.with_feats(torch.relu(self.net(x).feats + skip.feats))


def _cat(a: SparseTensor, b: SparseTensor) -> SparseTensor:
    assert a.stride == b.stride and torch.equal(a.coords, b.coords)
    return a.with_feats(torch.cat([a.feats, b.feats], dim=1))


class MinkUNet(nn.Module):
    def __init__(self, in_channels: int = 4, cr: float = 1.0):
        super().__init__()
        cs = [int(round(cr * c)) for c in CHANNELS]
        self.out_channels = cs[8]
        self.inputs = "xyz-opacity" if in_channels == 4 else "height-opacity"  # see INPUT_RECIPES
        self.stem = nn.Sequential(*_conv_bn_relu(in_channels, cs[0], 3, 1), *_conv_bn_relu(cs[0], cs[0], 3, 1))
        for i, (a, b) in enumerate([(cs[0], cs[1]), (cs[1], cs[2]), (cs[2], cs[3]), (cs[3], cs[4])], start=1):
            setattr(self, f"stage{i}", nn.Sequential(BasicBlock(a, a), ResidualBlock(a, b), ResidualBlock(b, b)))
        for i, (a, b, skip) in enumerate(
            [(cs[4], cs[5], cs[3]), (cs[5], cs[6], cs[2]), (cs[6], cs[7], cs[1]), (cs[7], cs[8], cs[0])], start=1
        ):
            setattr(
                self,
                f"up{i}",
                nn.ModuleList(
                    [BasicBlock(a, b, transpose=True), nn.Sequential(ResidualBlock(b + skip, b), ResidualBlock(b, b))]
                ),
            )
        self.eval()

    def forward(self, x: SparseTensor) -> SparseTensor:
        x0 = self.stem(x)
        skips = [x0]
        for i in range(1, 5):
            skips.append(getattr(self, f"stage{i}")(skips[-1]))
        y = skips[4]
        for i in range(1, 5):
            up = getattr(self, f"up{i}")
            y = up[1](_cat(up[0](y), skips[4 - i]))
        return y


def load_minkunet(path: str | Path) -> MinkUNet:
    """A MinkUNet with the checkpoint's weights (see the module docstring for the layout); its
    ``inputs`` attribute names the checkpoint's input recipe."""
    path = Path(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise SceneFormatError(path, "does not exist") from None
    except Exception as exc:  # torch raises many kinds for a file that is not a checkpoint
        raise SceneFormatError(path, f"not a PyTorch checkpoint ({type(exc).__name__}: {exc})") from None
    record = data.get("olsplat", {}) if isinstance(data, dict) else {}
    inputs = record.get("inputs", "xyz-opacity") if isinstance(record, dict) else "xyz-opacity"
    if inputs not in INPUT_RECIPES:
        raise SceneFormatError(path, f"unknown input recipe {inputs!r} (known: {', '.join(INPUT_RECIPES)})")
    for key in ("model", "model_state_dict", "state_dict"):
        if isinstance(data, dict) and isinstance(data.get(key), dict):
            data = data[key]
            break
    if not isinstance(data, dict):
        raise SceneFormatError(path, "holds no state dict")
    state = {k.removeprefix("module."): v for k, v in data.items()}
    stem = state.get("stem.0.kernel")
    if not isinstance(stem, torch.Tensor) or stem.ndim != 3 or stem.shape[0] != 27:
        raise SceneFormatError(
            path, "not a MinkUNet checkpoint of this layout: no stem.0.kernel of shape [27, C_in, C]"
        )
    in_channels, cr = int(stem.shape[1]), stem.shape[2] / CHANNELS[0]
    if in_channels != INPUT_RECIPES[inputs]:
        raise SceneFormatError(
            path, f"takes {in_channels} input channels; its recipe {inputs!r} gives {INPUT_RECIPES[inputs]}"
        )
    model = MinkUNet(in_channels, cr)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [
        f"{k} {tuple(state[k].shape)} (expected {tuple(expected[k].shape)})"
        for k in expected
        if k in state and tuple(state[k].shape) != tuple(expected[k].shape)
    ]
    if missing or unexpected or wrong:
        parts = [f"{len(missing)} missing keys (first: {', '.join(missing[:3])})" if missing else "",
                 f"{len(unexpected)} unexpected keys (first: {', '.join(unexpected[:3])})" if unexpected else "",
                 f"shape mismatches: {'; '.join(wrong[:3])}" if wrong else ""]  # fmt: skip
        raise SceneFormatError(path, "not a MinkUNet checkpoint of this layout: " + ", ".join(p for p in parts if p))
    model.load_state_dict({k: v.float() for k, v in state.items()})
    model.inputs = inputs
    return model.eval()


INPUT_RECIPES = {"xyz-opacity": 4, "height-opacity": 3}  # recipe -> input channels


def minkunet_point_features(model: MinkUNet, points: StructuralPoints, camera_centres: np.ndarray) -> np.ndarray:
    """[P, out_channels] float32 features of the point set, through the model's input recipe.
    Points sharing a voxel share its input (their mean) and its output."""
    if model.inputs == "height-opacity":
        frame = ground_frame(points, camera_centres)
        voxels, inputs = frame.voxels, frame.inputs
    else:
        centred = points.positions - points.positions.mean(0)
        voxels = points.positions / points.voxel
        inputs = np.c_[centred / max(np.abs(centred).max(), 1e-12), points.opacity].astype(np.float32)
    coords, voxel_inputs, inverse = voxelise(voxels, inputs)
    with torch.no_grad():
        out = model(SparseTensor(torch.from_numpy(coords), torch.from_numpy(voxel_inputs), 1))
    # the network returns to the input coordinates at stride 1, in the same row order
    return out.feats.numpy().astype(np.float32)[inverse]
