"""Committed leaderboards as the benchmark scripts read them: a board from a directory or
from any git revision, and its rows keyed by (method, setting)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path


def load(suite: str, directory: str | Path = "leaderboards") -> dict:
    """``<directory>/<suite>.json``."""
    return json.loads((Path(directory) / f"{suite}.json").read_text())


def at_revision(suite: str, rev: str) -> dict:
    """The board of ``suite`` as committed at git revision ``rev``."""
    out = subprocess.run(["git", "show", f"{rev}:leaderboards/{suite}.json"],
                         capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"no {suite} board at {rev}: {out.stderr.strip()}")
    return json.loads(out.stdout)


def keyed(board: dict, needed: list[str] | None = None) -> dict[tuple[str, str], dict]:
    """``board``'s rows by (method, setting); exits naming any of ``needed`` not on it."""
    rows = {(r["method"], r["setting"]): r for r in board["rows"]}
    missing = sorted(set(needed or []) - {m for m, _ in rows})
    if missing:
        raise SystemExit(f"not on the {board['suite']} board: {', '.join(missing)}")
    return rows
