"""CLIP's byte-pair-encoding tokenizer, from a user-supplied merges file.

The same algorithm and text cleaning as OpenAI CLIP / open_clip (ftfy, HTML unescaping,
whitespace folding, lower case; the same split pattern; byte-level BPE with ``</w>`` marking
word ends), so token ids match theirs for the same ``bpe_simple_vocab_16e6.txt.gz``. Token
sequences are ``[start] tokens [end] 0 0 ...`` of ``context_length``, cut to fit with the end
token kept.
"""

from __future__ import annotations

import gzip
import html
import json
from functools import lru_cache
from itertools import pairwise
from pathlib import Path

import ftfy
import numpy as np
import regex

START, END = "<|startoftext|>", "<|endoftext|>"
CLIP_MERGES = 49152 - 256 - 2  # CLIP keeps this many merges: a vocabulary of 49,408 tokens
_SPLIT = regex.compile(
    r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+""", regex.IGNORECASE
)


@lru_cache
def bytes_to_unicode() -> dict[int, str]:
    """A reversible map of the 256 byte values to printable unicode characters (GPT-2's)."""
    printable = (
        list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    )
    chars = printable[:]
    extra = 0
    for b in range(256):
        if b not in printable:
            printable.append(b)
            chars.append(256 + extra)
            extra += 1
    return dict(zip(printable, map(chr, chars), strict=True))


def clean(text: str) -> str:
    text = ftfy.fix_text(text)
    text = html.unescape(html.unescape(text)).strip()
    return " ".join(text.split()).lower()


class ClipTokenizer:
    def __init__(self, merges_path: str | Path, context_length: int = 77, max_merges: int | None = CLIP_MERGES):
        path = Path(merges_path)
        try:
            opener = gzip.open if path.suffix == ".gz" else open
            with opener(path, "rt", encoding="utf-8") as f:
                lines = f.read().split("\n")
        except (OSError, UnicodeDecodeError, EOFError) as exc:
            raise ValueError(f"{path}: not a readable BPE merges file ({type(exc).__name__}: {exc})") from None
        merges = [tuple(line.split()) for line in lines[1:] if line.strip()]
        merges = merges[:max_merges] if max_merges else merges
        if not merges or any(len(m) != 2 for m in merges):
            raise ValueError(f"{path}: not a BPE merges file (expected a header line, then 'a b' pairs)")
        symbols = list(bytes_to_unicode().values())
        vocab = symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges] + [START, END]
        self.encoder = {token: i for i, token in enumerate(vocab)}
        self.ranks = {merge: i for i, merge in enumerate(merges)}
        self.byte_encoder = bytes_to_unicode()
        self.context_length = context_length
        self.start_id, self.end_id = self.encoder[START], self.encoder[END]
        self.path = path
        self._cache: dict[str, str] = {}

    @property
    def vocab_size(self) -> int:
        return len(self.encoder)

    def _bpe(self, token: str) -> str:
        if token in self._cache:
            return self._cache[token]
        word = (*token[:-1], token[-1] + "</w>")
        while len(word) > 1:
            pairs = set(pairwise(word))
            best = min(pairs, key=lambda pair: self.ranks.get(pair, float("inf")))
            if best not in self.ranks:
                break
            merged, i = [], 0
            while i < len(word):
                if i < len(word) - 1 and (word[i], word[i + 1]) == best:
                    merged.append(word[i] + word[i + 1])
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = tuple(merged)
        self._cache[token] = " ".join(word)
        return self._cache[token]

    def encode(self, text: str) -> list[int]:
        """Token ids of ``text`` without start/end tokens."""
        ids: list[int] = []
        for piece in _SPLIT.findall(clean(text)):
            piece = "".join(self.byte_encoder[b] for b in piece.encode("utf-8"))
            ids.extend(self.encoder[t] for t in self._bpe(piece).split(" "))
        return ids

    def __call__(self, texts: list[str]) -> np.ndarray:
        """[T, context_length] int64: start, tokens, end, zero padding (cut keeping the end token)."""
        out = np.zeros((len(texts), self.context_length), np.int64)
        for row, text in enumerate(texts):
            ids = [self.start_id, *self.encode(text)[: self.context_length - 2], self.end_id]
            out[row, : len(ids)] = ids
        return out


class WordTokenizer:
    """Whole-word tokens for the shipped compact encoders: 0 = padding, 1 = unknown word.

    ``vocab`` is the list of known words (ids 2, 3, ...), read from a JSON file. Text is
    cleaned like CLIP's (see ``clean``) and split into runs of letters or digits; an unknown
    word ending in "s" whose singular is known takes the singular's id ("buildings").
    """

    PAD, UNKNOWN = 0, 1

    def __init__(self, vocab_path: str | Path, context_length: int = 16):
        path = Path(vocab_path)
        try:
            words = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable word list ({type(exc).__name__}: {exc})") from None
        if not isinstance(words, list) or not all(isinstance(w, str) for w in words):
            raise ValueError(f"{path}: a word vocabulary must be a JSON list of strings")
        self.ids = {word: i + 2 for i, word in enumerate(words)}
        self.context_length = context_length
        self.path = path

    @property
    def vocab_size(self) -> int:
        return len(self.ids) + 2

    def _id(self, word: str) -> int:
        if word in self.ids:
            return self.ids[word]
        return self.ids.get(word[:-1], self.UNKNOWN) if word.endswith("s") and len(word) > 3 else self.UNKNOWN

    def words(self, text: str) -> list[str]:
        return regex.findall(r"[\p{L}\p{N}]+", clean(text))

    def unknown_words(self, text: str) -> list[str]:
        """The words of ``text`` this vocabulary does not hold (they all map to one 'unknown' token)."""
        return [w for w in self.words(text) if self._id(w) == self.UNKNOWN]

    def __call__(self, texts: list[str]) -> np.ndarray:
        """[T, context_length] int64 word ids, zero padded, cut at context_length."""
        out = np.zeros((len(texts), self.context_length), np.int64)
        for row, text in enumerate(texts):
            ids = [self._id(w) for w in self.words(text)][: self.context_length]
            out[row, : len(ids)] = ids
        return out
