"""The master's live progress line, and the small side file ``campaign status`` reads.

On a terminal the line is rewritten in place on stderr (``\\r``); otherwise the
master stays quiet until its final summary. Every second or so the same figures go to
``OUT.progress.json`` (written atomically), so that ``campaign status OUT`` can show what
is running and the ETA while a run writes.

The file also says who writes: host, pid, the process's start time and the machine's
boot id. ``writer_state`` decides from it whether that run is alive: on the same host,
by looking at the process (gone, or a different process under a reused pid: dead); on
another host, by the file's age (a running master rewrites it at least every
``HEARTBEAT_SECONDS``, also while it compiles or writes; older than ``STALE_SECONDS``:
presumed dead).
"""

from __future__ import annotations

import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

from campaign.storage.faults import write_fault

#: A running master rewrites its progress file at least this often (seconds).
HEARTBEAT_SECONDS = 10.0
#: Seen from another host, a progress file older than this (seconds) means its run is dead.
STALE_SECONDS = 60.0


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


# --------------------------------------------------------------------------- who is writing

def _boot_id():
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def process_start(pid) -> int | None:
    """When process ``pid`` started (clock ticks since boot: /proc/PID/stat, field 22), or
    None if there is no such process (or no /proc)."""
    try:
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except (OSError, ValueError):
        return None
    try:
        return int(stat[stat.rindex(")") + 2:].split()[19])
    except (ValueError, IndexError):
        return None


def writer_identity() -> dict:
    """This process as the progress file names it."""
    return {"pid": os.getpid(), "host": socket.gethostname(), "pid_start": process_start(os.getpid()),
            "boot_id": _boot_id()}


def _pid_alive(pid, start) -> bool | None:
    """Is process ``pid`` (started at ``start`` ticks, when known) running on this host?"""
    try:
        pid = int(pid)
    except (TypeError, ValueError):
        return None
    if Path("/proc/self/stat").exists():
        now = process_start(pid)
        if now is None:
            return False
        return start is None or now == int(start)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return None
    return True


def writer_state(live: dict | None, now: float | None = None) -> dict:
    """Is the run that wrote the progress file ``live`` (``read_sidecar``) still running?

    Returns ``{"state", "how", "age", "text"}``: state ``"running"``, ``"dead"`` (same host:
    its process is gone, or its pid now belongs to another process; another host: no
    update for more than STALE_SECONDS), ``"ended"`` (it stopped and said so) or
    ``"none"`` (no progress file); how ``"pid"`` or ``"age"``; age in seconds.
    """
    now = time.time() if now is None else now
    if not live:
        return {"state": "none", "how": None, "age": None, "text": "no run is writing it"}
    age = max(0.0, now - float(live.get("updated", 0) or 0))
    who = f"pid {live.get('pid')} on {live.get('host')}"
    if not live.get("active"):
        return {"state": "ended", "how": None, "age": age, "text": "no run is writing it"}
    if live.get("host") == socket.gethostname():
        boot = live.get("boot_id")
        alive = False if boot and _boot_id() and boot != _boot_id() else _pid_alive(live.get("pid"),
                                                                                     live.get("pid_start"))
        if alive is not None:
            if alive:
                return {"state": "running", "how": "pid", "age": age,
                        "text": f"a run is writing it ({who}, updated {fmt_duration(age)} ago)"}
            return {"state": "dead", "how": "pid", "age": age,
                    "text": f"no run is writing it: the run that was ({who}) is gone without closing it "
                            f"(killed, or its node failed); what it finished is kept, and rerunning it resumes"}
    if age <= STALE_SECONDS:
        return {"state": "running", "how": "age", "age": age,
                "text": f"a run is writing it ({who}, updated {fmt_duration(age)} ago; another host, so judged "
                        f"by the progress file's age: live while under {STALE_SECONDS:.0f} s)"}
    return {"state": "dead", "how": "age", "age": age,
            "text": f"no run is writing it, presumably: the run on another host ({who}) has not updated "
                    f"its progress file for {fmt_duration(age)} (more than "
                    f"{STALE_SECONDS:.0f} s): it died without closing the store; rerunning it resumes"}


# --------------------------------------------------------------------------- the writer side

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
        self.extra = {}  # facts of the run for campaign status (the number of GPU workers)
        self.phase = "starting"
        self.identity = writer_identity()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._beat = None

    def begin(self, **counts):
        """Say that a run is starting (it may compile for a minute) and keep saying it: a thread
        rewrites the file every HEARTBEAT_SECONDS until ``finish`` (``campaign status`` tells a
        live run on another host by that). Space errors are the main thread's business."""
        if self.sidecar is None:
            return
        self.state = dict({"done": 0, "failed": 0, "running": 0, "remaining": self.total,
                           "per_hour": None, "eta_seconds": None}, **counts)
        self.write_sidecar()
        if self._beat is None:
            self._beat = threading.Thread(target=self._heartbeat, name="campaign-progress-heartbeat", daemon=True)
            self._beat.start()

    def _heartbeat(self):
        while not self._stop.wait(HEARTBEAT_SECONDS):
            try:
                self.write_sidecar()
            except Exception:  # noqa: BLE001 - the master's own writes report a full disk
                pass

    def update(self, *, done, failed, running, remaining, cost_remaining, finished_now=0,
               cost_now=0.0, force=False):
        self.done_now += finished_now
        self.cost_done += cost_now
        self.phase = "running"
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
        """Write the progress file atomically (a temporary file renamed over it). A full disk
        raises OutOfSpace (the run stops); other errors are ignored (the file is a courtesy)."""
        if self.sidecar is None:
            return
        data = dict(self.state, updated=time.time(), active=not final, phase="ended" if final else self.phase,
                    **self.extra, **self.identity)
        tmp = self.sidecar.with_name(self.sidecar.name + ".tmp")
        text = json.dumps(data)
        with self._lock:
            try:
                tmp.write_text(text)
                os.replace(tmp, self.sidecar)
            except OSError as exc:
                try:
                    tmp.unlink()
                except OSError:
                    pass
                fault = write_fault(exc, self.sidecar, "writing the progress file", needed=len(text.encode()))
                if fault is not None and fault.out_of_space:
                    raise fault from None

    def _stop_heartbeat(self):
        self._stop.set()
        if self._beat is not None:
            self._beat.join(timeout=5.0)
            self._beat = None

    def finish(self):
        self._stop_heartbeat()
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
        self.write_sidecar(final=True)

    def stopped(self):
        """After a fault: say that no run writes any more, or, when even that cannot be written
        (a full disk), remove the file (removing needs no space), so that nobody sees a live run."""
        self._stop_heartbeat()
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
        try:
            self.write_sidecar(final=True)
        except Exception:  # noqa: BLE001
            try:
                self.sidecar.unlink()
            except (OSError, AttributeError):
                pass


def read_sidecar(path) -> dict | None:
    try:
        return json.loads(Path(str(path) + ".progress.json").read_text())
    except (OSError, ValueError):
        return None
