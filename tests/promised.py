"""Skips that CI must not take: the set-up (``make setup``) promises a browser, Ray and
open_clip's tokenizer files, and CI machines have the shared real data (``../shared/data``). On
a developer's machine a test without them skips with the reason; where the environment variable
``CI`` is set (``.ci/run`` sets it) the same test fails, so that a broken set-up cannot quietly
drop the browser, cluster, real-data or tokenizer coverage while the run stays green."""

from __future__ import annotations

import os
from typing import NoReturn

import pytest

# what each promise covers, as the failure names it
PROMISES = {
    "browser": "Debian's chromium (make setup installs it as root)",
    "ray": "Ray (olsplat[cluster], which make setup installs)",
    "shared data": "the shared real data at ../shared/data (every CI machine has it)",
    "tokenizer": "open_clip's tokenizer files in .venv/reference (make setup unpacks them)",
}


def in_ci() -> bool:
    """True where the environment variable CI is set to anything but "", "0" or "false"."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def skip_unless_ci(promise: str, reason: str) -> NoReturn:
    """Skip the running test (``reason``), or fail it in CI, where ``promise`` (a key of
    ``PROMISES``) must hold."""
    if promise not in PROMISES:
        raise KeyError(f"unknown promise {promise!r}; one of {sorted(PROMISES)}")
    if in_ci():
        pytest.fail(f"CI promises {PROMISES[promise]}, but {reason}", pytrace=False)
    pytest.skip(reason)
