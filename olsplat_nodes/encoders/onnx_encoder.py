"""An encoder run by onnxruntime from a folder with a manifest and two ONNX towers.

Made by ``olsplat export-clip`` (CLIP-family models, CLIP's BPE tokenizer) or shipped in the
package (compact models, whole-word tokenizer): the manifest's ``tokenizer`` says which.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from .base import normalize
from .crops import CropConfig
from .tokenizer import ClipTokenizer, WordTokenizer

MANIFEST = "encoder.json"  # an encoder folder's description (written by export.py)


class OnnxEncoder:
    """Implements ``VisionLanguageEncoder``. Every file problem raises OlsplatInputError naming the file."""

    def __init__(self, folder: str | Path, threads: int = 0):
        import onnxruntime as ort

        folder = Path(folder)
        manifest_path = folder / MANIFEST
        try:
            manifest = json.loads(manifest_path.read_text())
            self.name, self.dim = str(manifest["name"]), int(manifest["embed_dim"])
            self.input_size, context = int(manifest["image_size"]), int(manifest["context_length"])
            self.mean = np.asarray(manifest["mean"], np.float32)
            self.std = np.asarray(manifest["std"], np.float32)
            files = {key: folder / manifest[key] for key in ("image", "text", "vocab")}
            vocab_size = int(manifest["vocab_size"])
            tokenizer_kind = manifest.get("tokenizer", "clip-bpe")
            self.crop_config = CropConfig(**manifest["crop"]) if "crop" in manifest else None
            if tokenizer_kind not in ("clip-bpe", "words"):
                raise ValueError(f"unknown tokenizer {tokenizer_kind!r}")
        except FileNotFoundError:
            raise OlsplatInputError(f"{manifest_path}: missing (make the folder with 'olsplat export-clip')") from None
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise OlsplatInputError(f"{manifest_path}: not an encoder manifest ({type(exc).__name__}: {exc})") from None
        for path in files.values():
            if not path.is_file():
                raise OlsplatInputError(f"{path}: missing (named by {manifest_path})")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.log_severity_level = 3
        self.sessions = {}
        for key in ("image", "text"):
            try:
                self.sessions[key] = ort.InferenceSession(str(files[key]), options, providers=["CPUExecutionProvider"])
            except Exception as exc:  # onnxruntime raises its own exception types
                raise OlsplatInputError(
                    f"{files[key]}: not a loadable ONNX model ({str(exc).splitlines()[0]})"
                ) from None
        self._check_io(files, context)
        try:
            make = ClipTokenizer if tokenizer_kind == "clip-bpe" else WordTokenizer
            self.tokenizer = make(files["vocab"], context_length=context)
        except ValueError as exc:
            raise OlsplatInputError(str(exc)) from None
        if self.tokenizer.vocab_size != vocab_size:
            raise OlsplatInputError(
                f"{files['vocab']}: {self.tokenizer.vocab_size} tokens, but the text tower was exported for "
                f"{vocab_size}: "
                "not the vocabulary of this text tower"
            )

    def _check_io(self, files: dict[str, Path], context: int) -> None:
        expected = {"image": [3, self.input_size, self.input_size], "text": [context]}
        for key, session in self.sessions.items():
            inputs, outputs = session.get_inputs(), session.get_outputs()
            shape = list(inputs[0].shape[1:]) if len(inputs) == 1 else None
            out_dim = outputs[0].shape[-1] if len(outputs) == 1 else None
            if shape != expected[key] or out_dim != self.dim:
                raise OlsplatInputError(
                    f"{files[key]}: takes {[i.shape for i in inputs]} and gives {[o.shape for o in outputs]}, but the "
                    f"manifest says [batch, {', '.join(map(str, expected[key]))}] -> [batch, {self.dim}]"
                )

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        """[B, S, S, 3] uint8 RGB -> [B, dim] unit rows."""
        if crops.ndim != 4 or crops.shape[1:] != (self.input_size, self.input_size, 3) or crops.dtype != np.uint8:
            raise ValueError(
                f"encoder {self.name!r} takes [B, {self.input_size}, {self.input_size}, 3] uint8 crops, "
                f"got shape {crops.shape} dtype {crops.dtype}"
            )
        pixels = ((crops.astype(np.float32) / 255.0 - self.mean) / self.std).transpose(0, 3, 1, 2)
        session = self.sessions["image"]
        return normalize(session.run(None, {session.get_inputs()[0].name: np.ascontiguousarray(pixels)})[0])

    def unknown_words(self, text: str) -> list[str]:
        """Words of ``text`` the text tower cannot tell apart (a word-level vocabulary; a BPE
        tokenizer, as CLIP's, spells any word and reports none)."""
        unknown = getattr(self.tokenizer, "unknown_words", None)
        return unknown(text) if unknown is not None else []

    def encode_text(self, texts: list[str]) -> np.ndarray:
        session = self.sessions["text"]
        return normalize(session.run(None, {session.get_inputs()[0].name: self.tokenizer(texts)})[0])
