"""What a scan of the campaign store found (``campaign.storage.integrity.scan``, ``campaign
verify``): ``Damage``, one damaged part and what a repair does with it, and ``Report``, all of
them, the rows a repair drops (``campaign.storage.repair``) and the JSON ``campaign verify
--json`` prints (docs/STORE.md, "Checksums, verify and repair").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.storage.layout import PENDING


@dataclass
class Damage:
    """One damaged part of a store.

    ``name``: the object (a dataset, a group, a root attribute ``/@name``); ``how``: what is wrong,
    a phrase; ``rows``: the finished task rows whose results it held (the tasks a repair makes
    pending); ``span``: the rows of a damaged block (first, last + 1); ``repair``: ``"drop"`` (its
    rows are dropped and recomputed), ``"rewrite"`` (rewritten from the spec: nothing is lost),
    ``"remove"`` (not carried over: nothing a task needs) or ``"none"`` (a repair cannot fix it)."""

    name: str
    how: str
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    span: tuple | None = None
    repair: str = "drop"
    labels: list = field(default_factory=list)  # "id (variant N=.. E=.. seed ..)" of the first rows
    note: str = ""  # what a repair does with it, when not the rule of ``repair``

    def held_text(self, limit=3) -> str:
        n = len(self.rows)
        if not n:
            return ""
        shown = ", ".join(self.labels[:limit]) if self.labels else ", ".join(f"row {r}" for r in self.rows[:limit])
        more = f" and {n - limit} more" if n > limit else ""
        return f"; it holds {n} finished task(s): {shown}{more}"

    def to_json(self) -> dict:
        return {"object": self.name, "problem": self.how, "rows": [int(r) for r in self.rows],
                "span": list(self.span) if self.span else None, "repair": self.repair, "repair_note": self.note,
                "tasks": self.labels}


@dataclass
class Report:
    path: str
    name: str = ""
    T: int = 0
    B: int = 0
    counts: dict = field(default_factory=lambda: {"done": 0, "failed": 0, "pending": 0})
    damage: list = field(default_factory=list)
    fatal: str | None = None          # the store cannot be opened or walked at all
    spec: object = None               # the stored spec, parsed (None if it cannot be, or its hash differs)
    edges: dict = field(default_factory=dict)  # readable, sound bin edges
    checked: dict = field(default_factory=lambda: {"datasets": 0, "chunks": 0, "bytes": 0, "configurations": 0,
                                                   "failures": 0, "seconds": 0.0})
    unchecked: dict = field(default_factory=lambda: {"datasets": [], "configurations": 0, "failures": 0})
    status: np.ndarray | None = None
    renames: dict = field(default_factory=dict)  # scalar datasets under a damaged name -> their name
    unprotected: bool = False         # the store has no block checksums (written before 0.3.0)
    protection: str = ""              # its block_checksums attribute: how it came to have them

    @property
    def ok(self) -> bool:
        return self.fatal is None and not self.damage

    def drop_rows(self) -> np.ndarray:
        """Rows a repair drops: the finished rows of every damaged part and the rows of every
        damaged block (pending ones there too: they hold nothing a task needs)."""
        parts = [np.zeros(0, np.int64)]
        for d in self.damage:
            if d.repair != "drop":
                continue
            parts.append(np.asarray(d.rows, np.int64))
            if d.span is not None:
                parts.append(np.arange(d.span[0], d.span[1], dtype=np.int64))
        return np.unique(np.concatenate(parts))

    def lost_rows(self) -> np.ndarray:
        """Finished rows a repair makes pending."""
        rows = self.drop_rows()
        if self.status is None:
            return rows
        rows = rows[rows < len(self.status)]
        return rows[self.status[rows] != PENDING]

    def unrepairable(self) -> list:
        out = [d for d in self.damage if d.repair == "none"]
        if self.fatal is None and self.spec is None and self.damage:
            out = out or [Damage("/@spec_yaml", "cannot be parsed into the spec that wrote the store", repair="none")]
        return out

    def to_json(self) -> dict:
        return {"file": self.path, "ok": self.ok, "name": self.name, "tasks": self.T, **self.counts,
                "fatal": self.fatal, "checked": self.checked,
                "without_checksums": dict(self.unchecked), "block_checksums": not self.unprotected,
                "damage": [d.to_json() for d in self.damage],
                "tasks_lost": int(len(self.lost_rows())),
                "repairable": self.fatal is None and not self.unrepairable()}
