"""The CI guard of tests/promised.py: a promised requirement that is missing skips a test on a
developer's machine and fails it where CI is set. Run on the real browser tests with chromium
taken off the PATH, in a child pytest."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .promised import PROMISES, in_ci, skip_unless_ci

ROOT = Path(__file__).resolve().parents[1]


def _browser_tests_without_chromium(tmp_path, ci: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["PATH"] = str(tmp_path)  # no chromium on it (the child is started by its full path)
    if ci is not None:
        env["CI"] = ci
    test = "tests/ground/test_web_page.py::test_the_page_follows_a_run_folder_being_written_without_a_reload"
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rsf", test],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def test_without_chromium_the_browser_tests_skip_outside_ci_and_fail_in_ci(tmp_path):
    outside = _browser_tests_without_chromium(tmp_path, None)
    assert outside.returncode == 0 and "1 skipped" in outside.stdout, outside.stdout[-2000:]
    assert "chromium is not installed" in outside.stdout
    inside = _browser_tests_without_chromium(tmp_path, "true")
    assert inside.returncode == 1, inside.stdout[-2000:]
    assert "CI promises Debian's chromium" in inside.stdout and "skipped" not in inside.stdout


def test_ci_is_read_as_people_set_it(monkeypatch):
    for value, expected in (("true", True), ("1", True), ("yes-please", True), ("", False), ("0", False),
                            ("false", False), ("FALSE", False)):  # fmt: skip
        monkeypatch.setenv("CI", value)
        assert in_ci() is expected, value
    monkeypatch.delenv("CI")
    assert not in_ci()
    with pytest.raises(KeyError, match="unknown promise"):
        skip_unless_ci("gpu", "no GPU")
    assert set(PROMISES) == {"browser", "ray", "shared data", "tokenizer"}
