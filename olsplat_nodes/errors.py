"""Errors that mean "the user gave us something we cannot use" or "the run did not get there".

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


class RunFailed(RuntimeError):
    """A run of the node graph ended without what it was started for (e.g. a benchmark's flight
    aggregated no view, or the query server refused its queries): an outcome to report, not a
    bug. The message says what happened and where the run's logs are."""


# Process exit codes of nodes, the launcher and the CLI.
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130
