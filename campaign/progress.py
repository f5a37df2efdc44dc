"""The master's live progress line, and the small side file ``campaign status`` reads.

On a terminal the line is rewritten in place on stderr (``\\r``); otherwise the
master stays quiet until its final summary. Every couple of seconds the same
figures go to ``OUT.progress.json`` (written atomically), so that
``campaign status OUT`` can show what is running and the ETA while a run writes.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path


def fmt_duration(seconds) -> str:
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "?"
    seconds = int(round(seconds))
    d, rem = divmod(seconds, 86400)
    h, rem = divmod(rem, 3600)
    m, s = divmod(rem, 60)
    return f"{d}d{h:02d}:{m:02d}:{s:02d}" if d else f"{h}:{m:02d}:{s:02d}"


def progress_text(p: dict) -> str:
    rate = p.get("per_hour")
    rate_s = f"{rate:,.0f} packings/h" if rate else "- packings/h"
    eta = "-" if not p["remaining"] and not p["running"] else fmt_duration(p.get("eta_seconds"))
    return (f"done {p['done']}  failed {p['failed']}  running {p['running']}  remaining {p['remaining']}"
            f"  | {rate_s}  ETA {eta}")


class Progress:
    def __init__(self, total: int, sidecar: Path | None = None, stream=None, enabled=None):
        self.total = total
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty() if enabled is None else enabled
        self.sidecar = Path(sidecar) if sidecar else None
        self.start = time.monotonic()
        self.last_line = 0.0
        self.last_file = 0.0
        self.done_now = 0          # finished in this run
        self.cost_done = 0.0       # estimated cost finished in this run
        self.state = {}

    def update(self, *, done, failed, running, remaining, cost_remaining, finished_now=0,
               cost_now=0.0, force=False):
        self.done_now += finished_now
        self.cost_done += cost_now
        now = time.monotonic()
        if not force and now - self.last_line < 0.25:
            return
        elapsed = now - self.start
        per_hour = 3600.0 * self.done_now / elapsed if elapsed > 0 and self.done_now else None
        eta = cost_remaining * elapsed / self.cost_done if self.cost_done > 0 else None
        self.state = {"done": done, "failed": failed, "running": running, "remaining": remaining,
                      "per_hour": per_hour, "eta_seconds": eta}
        if self.tty:
            self.stream.write("\r" + progress_text(self.state) + "\x1b[K")
            self.stream.flush()
        self.last_line = now
        if self.sidecar is not None and (force or now - self.last_file >= 1.0):
            self.write_sidecar()
            self.last_file = now

    def write_sidecar(self, final=False):
        if self.sidecar is None:
            return
        data = dict(self.state, updated=time.time(), pid=os.getpid(), host=socket.gethostname(),
                    active=not final)
        tmp = self.sidecar.with_name(self.sidecar.name + ".tmp")
        try:
            tmp.write_text(json.dumps(data))
            os.replace(tmp, self.sidecar)
        except OSError:
            pass

    def finish(self):
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
        self.write_sidecar(final=True)


def read_sidecar(path) -> dict | None:
    try:
        return json.loads(Path(str(path) + ".progress.json").read_text())
    except (OSError, ValueError):
        return None
