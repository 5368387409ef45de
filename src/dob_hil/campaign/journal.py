"""The journal: one JSON line per finished case, appended and synced after every batch, so an
interrupted campaign resumes without redoing finished cases. The first line names the campaign
(its fingerprint); a journal of another campaign (or an edited one) is refused, not mixed in.
Floats are written with ``repr`` (JSON's own), so they read back bit for bit."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from dob_hil.errors import ConfigError


class Journal:
    def __init__(self, path: Path, fingerprint: str, name: str) -> None:
        self.path = path
        self.rows: dict[int, dict[str, Any]] = {}
        header = {"campaign": name, "fingerprint": fingerprint}
        if path.exists() and path.stat().st_size > 0:
            self._read(fingerprint)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", encoding="utf-8") as f:
                f.write(json.dumps(header) + "\n")

    def _read(self, fingerprint: str) -> None:
        with self.path.open("r", encoding="utf-8") as f:
            lines = f.read().split("\n")
        try:
            header = json.loads(lines[0])
        except json.JSONDecodeError:
            raise ConfigError(str(self.path), "not a campaign journal (first line)") from None
        if header.get("fingerprint") != fingerprint:
            raise ConfigError(
                str(self.path),
                "the journal belongs to another campaign or an edited one: use another --out or delete it",
            )
        for line in lines[1:]:
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:  # the last line of a killed write: that case is redone
                continue
            self.rows[int(row["index"])] = row

    def append(self, rows: list[dict[str, Any]]) -> None:
        with self.path.open("a", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(row) + "\n")
            f.flush()
            os.fsync(f.fileno())
        for row in rows:
            self.rows[int(row["index"])] = row
