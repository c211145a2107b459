"""One row of the pre-flight table, and the table itself."""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

Status = Literal["ok", "warn", "blocker"]
STATUSES: tuple[Status, ...] = ("ok", "warn", "blocker")


@dataclass(frozen=True)
class Row:
    """What one check found: ``status`` ok (nothing to do), warn (a flight runs, worse than it
    could) or blocker (do not fly: the fix first); ``figure`` the measured value in one short
    line, with its unit; ``fix`` the one-line remedy ("" when ok)."""

    name: str
    status: Status
    figure: str
    fix: str = ""


def ok(name: str, figure: str) -> Row:
    return Row(name, "ok", figure)


def warn(name: str, figure: str, fix: str) -> Row:
    return Row(name, "warn", figure, fix)


def blocker(name: str, figure: str, fix: str) -> Row:
    return Row(name, "blocker", figure, fix)


def blocked(rows: Iterable[Row]) -> bool:
    """Whether any row is a blocker (the CLI then exits 1)."""
    return any(row.status == "blocker" for row in rows)


def format_table(rows: Sequence[Row]) -> str:
    """The rows as an aligned text table (check, status, figure; the fix on the next line,
    indented, where there is one) and a last line counting each status."""
    name_w = max([len("check"), *(len(r.name) for r in rows)])
    lines = [f"{'check':<{name_w}}  {'status':<7}  figure", f"{'-' * name_w}  {'-' * 7}  {'-' * 6}"]
    for row in rows:
        lines.append(f"{row.name:<{name_w}}  {row.status:<7}  {row.figure}")
        if row.fix:
            lines.append(f"{'':<{name_w}}  {'':<7}  fix: {row.fix}")
    counts = {status: sum(r.status == status for r in rows) for status in STATUSES}
    verdict = "do not fly: fix the blockers first" if counts["blocker"] else "ready"
    lines.append(f"{counts['ok']} ok, {counts['warn']} warn, {counts['blocker']} blocker: {verdict}")
    return "\n".join(lines)


def write_json(rows: Sequence[Row], path: str | Path) -> None:
    """``{"rows": [{name, status, figure, fix}, ...], "blocked": bool}`` to ``path``."""
    data = {"rows": [asdict(row) for row in rows], "blocked": blocked(rows)}
    Path(path).write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
