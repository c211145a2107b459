"""Scene I/O: the Gaussian map (INRIA PLY) and cameras (COLMAP, transforms.json)."""

from .camera import Camera, intrinsics, look_at
from .colmap import read_colmap, write_colmap
from .gaussians import Gaussians
from .load import read_cameras, select_view
from .ply import read_ply, write_ply
from .transforms_json import read_transforms_json, write_transforms_json

__all__ = [
    "Camera",
    "Gaussians",
    "intrinsics",
    "look_at",
    "read_cameras",
    "read_colmap",
    "read_ply",
    "read_transforms_json",
    "select_view",
    "write_colmap",
    "write_ply",
    "write_transforms_json",
]
