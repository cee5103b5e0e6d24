"""Append-only, resumable storage of per-episode results (one JSON line per episode)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any


class ResultStore:
    """``<root>/<suite>/<method>.jsonl``: one row per (setting, instance, trial).

    Rows are appended and fsync'ed chunk by chunk, so an interrupted run loses at most the
    chunk in flight; a torn last line (killed mid-write) is ignored and rewritten.
    """

    def __init__(self, root: str | Path, suite: str) -> None:
        self.dir = Path(root) / suite
        self.dir.mkdir(parents=True, exist_ok=True)

    def path(self, method: str) -> Path:
        return self.dir / f"{method}.jsonl"

    def rows(self, method: str) -> list[dict[str, Any]]:
        path = self.path(method)
        if not path.exists():
            return []
        rows = []
        for line in path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:  # torn write of an interrupted run
                continue
        return rows

    def done(self, method: str, **match: Any) -> set[tuple[str, int, int]]:
        """Keys (setting, instance, trial) already stored for ``method`` (only rows whose
        fields equal ``match``, e.g. the checkpoint a learned method's rows came from)."""
        return {(r["setting"], r["instance"], r["trial"]) for r in self.rows(method)
                if all(r.get(k) == v for k, v in match.items())}

    def append(self, method: str, rows: Iterable[dict[str, Any]]) -> None:
        path = self.path(method)
        text = "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows)
        # Drop a torn last line left by a killed writer before appending.
        if path.exists():
            raw = path.read_bytes()
            if raw and not raw.endswith(b"\n"):
                path.write_bytes(raw[: raw.rfind(b"\n") + 1])
        with open(path, "a") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
