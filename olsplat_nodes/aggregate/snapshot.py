"""The language map: one feature per Gaussian plus what it takes to embed text the same way.

Saved as one ``.npz`` (written to a temp file, then renamed: readers never see half a map):
``features`` [N, D] float16 (unit rows; zero rows for never-observed Gaussians), ``observed``
[N] bool, ``encoder`` (the encoder or fusion spec text), ``version``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SceneFormatError

FORMAT_VERSION = 1


@dataclass
class LanguageMap:
    features: np.ndarray  # [N, D] float16 or float32, unit rows (0 for unobserved)
    observed: np.ndarray  # [N] bool
    encoder: str  # e.g. "shipped:0.6,0.4" or "enc/remoteclip,enc/georsclip:0.6,0.4"

    @staticmethod
    def from_features(features: np.ndarray, observed: np.ndarray, encoder: str) -> "LanguageMap":
        norm = np.linalg.norm(features, axis=1, keepdims=True)
        unit = np.where(norm > 0, features / np.maximum(norm, 1e-12), 0.0)
        return LanguageMap(unit.astype(np.float16), observed.astype(bool), encoder)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, features=self.features, observed=self.observed, encoder=np.array(self.encoder), version=FORMAT_VERSION)
        tmp.replace(path)

    @staticmethod
    def load(path: str | Path) -> "LanguageMap":
        path = Path(path)
        try:
            data = np.load(path)
            if int(data["version"]) != FORMAT_VERSION:
                raise SceneFormatError(path, f"language map version {int(data['version'])}, this olsplat reads {FORMAT_VERSION}")
            return LanguageMap(data["features"], data["observed"], str(data["encoder"]))
        except FileNotFoundError:
            raise SceneFormatError(path, "does not exist") from None
        except (KeyError, ValueError, OSError) as exc:
            raise SceneFormatError(path, f"not a language map ({type(exc).__name__}: {exc})") from None
