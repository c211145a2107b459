"""Errors that mean "the user gave us something we cannot use" or "the run did not get there".

The CLI prints these as one line (no traceback) and exits non-zero; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

import errno
from pathlib import Path


class OlsplatInputError(ValueError):
    """Bad user input: a file, a parameter or a name. The message says which and why."""


class SceneFormatError(OlsplatInputError):
    """A scene or camera file that cannot be read; the message names the file and the problem."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ParameterError(OlsplatInputError):
    """A parameter that cannot be used; the message starts with where it came from and its name
    (``params.py`` checks parameters; the class lives here so that ``classify_failure`` needs no
    import from above)."""


class RunFailed(RuntimeError):
    """A run of the node graph ended without what it was started for (e.g. a benchmark's flight
    aggregated no view, or the query server refused its queries): an outcome to report, not a
    bug. The message says what happened and where the run's logs are."""


# Process exit codes of nodes, the launcher and the CLI.
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130
# A node's exit codes for a failure that a restart cannot mend (sysexits.h): its input cannot be
# used (a truncated or NaN map, a cut replay log: ``OlsplatInputError``, ``SceneFormatError``)
# or its configuration or environment is wrong (``ParameterError``, an endpoint already bound by
# another process). The node writes one line ``node NAME: error: REASON`` (no traceback) before
# it exits; the launcher does not restart it, prints ``NAME: REASON`` and stops the launch.
EXIT_BAD_INPUT, EXIT_CONFIG = 65, 78  # EX_DATAERR, EX_CONFIG
NOT_RESTARTABLE = (EXIT_BAD_INPUT, EXIT_CONFIG)

# errno values of a bind that fails on the machine's state, not on a bug: in use, not an address
_BIND_ERRNOS = (errno.EADDRINUSE, errno.EADDRNOTAVAIL, errno.EACCES)


def classify_failure(exc: BaseException) -> tuple[int, str] | None:
    """``(exit code, one-line reason)`` when ``exc`` is a failure a restart cannot mend: bad
    input (``OlsplatInputError`` and its subclasses, a missing file) -> ``EXIT_BAD_INPUT``; a
    parameter error or a socket that cannot be bound (``zmq.ZMQError`` "Address already in use",
    recognised by its errno and the transport's "while binding ENDPOINT" note) -> ``EXIT_CONFIG``.
    None for anything else (a crash: restarted)."""
    if isinstance(exc, ParameterError):
        return EXIT_CONFIG, _one_line(str(exc))
    if isinstance(exc, (OlsplatInputError, FileNotFoundError)):
        return EXIT_BAD_INPUT, _one_line(str(exc))
    notes = [n for n in getattr(exc, "__notes__", ()) if n.startswith("while binding ")]
    code = getattr(exc, "errno", None)
    # an address in use or not of this machine only ever comes from a bind; EACCES only with the note
    if code in _BIND_ERRNOS and (notes or code != errno.EACCES):
        endpoint = f" {notes[-1][len('while binding ') :]}" if notes else ""
        return EXIT_CONFIG, _one_line(f"cannot bind{endpoint}: {exc} (is another graph running?)")
    return None


def _one_line(text: str) -> str:
    return " ".join(text.split())
