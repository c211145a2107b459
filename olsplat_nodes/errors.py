"""Errors that mean "the user gave us something we cannot use".

The CLI prints these as one line (no traceback) and exits non-zero; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class OlsplatInputError(ValueError):
    """Bad user input: a file, a parameter or a name. The message says which and why."""


class SceneFormatError(OlsplatInputError):
    """A scene or camera file that cannot be read; the message names the file and the problem."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


# Process exit codes of nodes, the launcher and the CLI.
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130
