"""The master's writer of a campaign store: a run's start (opening or resuming the store), its
finished tasks staged and written block by block, checkpoints, and its close (docs/STORE.md).

Two files, written only by the master: the HDF5 store (``OUT``, its layout ``campaign.storage.layout``:
per-task datasets chunked by blocks of rows, ``tasks/status`` the commit marker) and its write-ahead
journal (``OUT.journal``, ``campaign.storage.journal``: one record per finished task, written before
anything touches the HDF5 file, cut back at a *checkpoint* once the store holds everything).

A run's start (``Store._open``): the journal is read and the file looked at once (``layout.inspect``):
kept, salvaged from its readable rows when it is damaged (``campaign.storage.salvage``) or created,
each giving the scheduler's ``layout.State``; a store of another spec or program is refused
(``layout.ForeignStore``). Then it is opened for writing, the journal replayed into it (idempotent: a
row is a pure function of its last record; rows lost with damage are counted and run again, packings
being pure functions of the spec) and both are checkpointed.

The master keeps O(1) per task in memory: status, attempts and wall time (the scheduler and the
wall-time model need them). A finished task's scalars and histograms wait in a staging buffer only
until the block of rows they belong to is complete (or ``HOLD_SECONDS`` have passed, or the buffer
passes ``BUFFER_BYTES``), then go to disk: data first, ``flush``, then the status column, ``flush``
again. Writing whole blocks keeps each compressed chunk written about once. A chunk rewritten whole
could lose its committed rows to a write cut by SIGKILL, so before a block is written again, its
committed rows that are no longer in the journal are appended to it again (from the store).

A full disk (or quota, or a failing file system) never leaves the two files disagreeing: every HDF5
write step first reserves the space it may need (``campaign.storage.space``) and raises
``OutOfSpace`` before writing anything; should HDF5 itself meet a failed write, its handle is
*poisoned* (``campaign.storage.faults.GuardedFile.poisoned``) and never flushed or closed normally
again, and the next start salvages the store from the journal. Either way the run stops with a
``WriteFault`` (exit status 3).

Suspended GPU packings (stop and go, docs/GPU.md) take the same path: a ``suspended`` record in the
journal first (``Store.suspend``), then the group ``/checkpoints/<id>`` (the packing's state and
counters, with a checksum) at the next flush; the task stays pending, and the group is removed in the
write step that commits the task's row. A checkpoint that cannot be read or does not match its
checksum is ignored (``Store.suspended``): its task starts over.

Calls go one way: here -> ``space``, ``salvage``, ``layout``, ``checksums``, ``journal``,
``faults`` and ``reader`` (the readers' error, should the task table not read); none of them
imports this module.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from campaign.errors import OutOfSpace, StoreDamaged, UserError
from campaign.storage.faults import GuardedFile, write_fault
from campaign.storage.layout import BLOCK_ROWS  # rows per chunk of every per-task dataset
from campaign.storage.checksums import (CHECKPOINT_ATTRS, CHECKPOINT_KEYS, CONFIG_KEYS, ROUNDS_GROUP, BlockMismatch,
                                        check_configuration, check_rows, checkpoint_problem, checksums_on,
                                        create_fill_sums, has_sums, read_rounds, sums_name, unprotected_note,
                                        write_checkpoint, write_configuration, write_failure, write_round,
                                        write_scalar_names, write_sums)
from campaign.storage.journal import Journal, task_record
from campaign.storage.journal import (  # noqa: F401 - part of this module's interface
    MAX_RECORD, decode_payload, encode_record, read_journal, scan_journal)
from campaign.storage.layout import (  # noqa: F401 - part of this module's interface
    CHUNK_CACHE, COMPRESSION, DONE, ERROR_LEN, FAILED, FORMAT_VERSION, HOST_LEN, OLD_FORMAT_HELP, PENDING,
    ROW_FIELDS, SCHEMA, SLACK, TASK_FIELDS, VARIANT_LEN, State, block_values, check_format, column_block,
    create_file, dataset_kwargs, fill_value, fixed, format_problem, fsync_path, inspect, row_dtype, row_values)
from campaign.storage.reader import read_failure
from campaign.storage.salvage import salvage
from campaign.storage.space import StoreSpace

FLUSH_SECONDS = 0.5     # staged complete blocks are written at least this often
HOLD_SECONDS = 2.0      # a block still partly pending is written after waiting this long
BUFFER_BYTES = 96 << 20  # staged rows beyond this are written whether their block is complete or not
JOURNAL_BYTES = 64 << 20  # checkpoint when the journal grows past this


def peak_rss_mb() -> float:
    """This process's peak resident memory so far (MB), as the kernel counts it: the master's,
    recorded in the run's record when the store closes."""
    try:
        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)  # kB on Linux
    except OSError:
        return float("nan")


class Store:
    """The master's view of one campaign file. Not thread-safe; one per process.

    In memory per task: ``status`` (int8), ``attempts`` (int32), ``wall`` (float64).
    Everything else is read from the file (or the staging buffer) when asked:
    ``read(column, index)``, ``configuration(index)``.
    """

    def __init__(self, path, spec, tasks, edges: dict, *, new=False, provenance=None, log=None):
        self.path = Path(path)
        self.spec, self.tasks = spec, tasks
        self.T = len(tasks)
        self.B = max(1, min(BLOCK_ROWS, self.T))
        self.edges = {k: np.asarray(v, np.float64) for k, v in sorted(edges.items())}
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.f = self.io = self.space = self.journal = None
        _make_directory(self.path)
        try:
            self._open(new, provenance or {})
        except BaseException:
            self.abandon()
            raise

    # ---- opening, refusing, salvaging, replaying
    def _open(self, new, provenance):
        """The journal (locked: one writer), then one look at the file with a verdict (ForeignStore:
        another spec's or program's), then the file kept, salvaged or created, each giving the
        scheduler's ``State``; then one open for writing loads what the run keeps, the journal is
        replayed on top and both are checkpointed."""
        self.journal = Journal(Path(str(self.path) + ".journal"))  # locked: one writer per store
        if new:
            self.journal.clear()
            self.path.unlink(missing_ok=True)
        replay = self.journal.replay(self.spec.hash)
        # blocks a killed run may have left half written (rows and checksums out of step): the journal
        # rewrites them, so reading them back does not check their checksums
        self.unsure = {i // self.B for i in replay.rows()}
        committed, notes = replay.committed, replay.notes()
        try:
            verdict = inspect(self.path, self.spec.hash, self.tasks, self.edges, self.B, self.unsure)
        except (OSError, KeyError, ValueError, RuntimeError) as exc:  # a sound store whose state does not read
            raise read_failure(self.path, exc, None, ["tasks/attempts", "tasks/wall"],
                               what="its task table") from None
        state = verdict.state
        if verdict.action == "salvage" and not replay.found:
            raise UserError(f"{str(self.path)!r} is unreadable ({verdict.problem}) and has no journal to rebuild it "
                            f"from. `campaign verify {self.path}` says what is damaged, and `--repair` rebuilds "
                            "it from its readable rows; or move it away, or rerun with --new")
        if verdict.action == "salvage":
            self.log(f"campaign: {self.path} is damaged ({verdict.problem}); salvaging its readable rows into a "
                     "new file and replaying the journal")
            state = salvage(self.path, self.spec, self.tasks, self.edges, self.B)
        elif verdict.action == "create":
            create_file(self.path, self.spec, self.tasks, self.edges, self.B)
            state = State.fresh(self.T)
        # the space accounting (what a write step may add, its reservation, what finishing needs),
        # told once which blocks the file holds
        self.space = StoreSpace(self.path, self.B, self.T, self.edges,
                                written=(np.flatnonzero(state.status != PENDING) // self.B).tolist())
        self._load(state)
        self.run = dict(provenance, start=_now(), end=None, run_id=os.urandom(8).hex())
        self._replay(replay.records)
        del replay  # the records not staged any more need not stay in memory
        lost = committed - self.n_final()
        if verdict.action != "keep" and lost > 0:
            where = "the damaged part of the" if verdict.action == "salvage" else "the missing"
            self.log(f"campaign: at least {lost} finished task(s) were only in {where} store; they are "
                     "pending again and will be run again")
        for note in notes:
            self.log(note)
        self._merge_run(self.run)
        self._write_root_attrs()
        self.checkpoint()

    def _load(self, state):
        """Open the file for writing (the file system's refusal: a WriteFault) and take what the run
        keeps in memory: the scheduler's ``state``, the groups the file holds, its round decisions and
        runs."""
        try:
            self.io = GuardedFile(self.path)
        except OSError as exc:
            fault = write_fault(exc, self.path, "opening the store for writing")
            if fault is None:
                raise
            raise fault from None
        self.f = f = h5py.File(self.io, "r+", rdcc_nbytes=CHUNK_CACHE)
        self.status, self.attempts, self.wall = state.status, state.attempts, state.wall
        self._datasets = {}
        self._sums = {} if has_sums(f) else None  # dataset name -> its block checksums
        if self._sums is None and checksums_on():  # a store of 0.2.7 or older: it stays as it is
            self.log(f"campaign: {unprotected_note(self.path)} (this run adds none to it)")
        self.have_configs = set(f["configurations"].keys()) if "configurations" in f else set()
        try:  # suspended packings (stop and go); a group that cannot be listed holds none we trust
            self.have_checkpoints = set(f["checkpoints"].keys()) if "checkpoints" in f else set()
        except Exception:  # noqa: BLE001 - its tasks start over
            self.log(f"campaign: {self.path}: the suspended packings (checkpoints) cannot be listed; their "
                     "tasks start over")
            self.have_checkpoints = set()
        self.have_failures = set(f["failures"].keys()) if "failures" in f else set()
        self._rerun_unrecorded_failures()
        self.n_status = state.counts()  # pending, done, failed; kept up to date by _stage
        self.rounds_stored: dict[int, dict] = {}        # a precision campaign's decisions in the file
        if ROUNDS_GROUP in f:  # a precision campaign's decisions so far (a fixed grid has none)
            self.rounds_stored, problems = read_rounds(f)
            if problems:
                self.log(f"campaign: {self.path}: {len(problems)} round decision(s) cannot be used ("
                         + "; ".join(problems[:3]) + "); they are made again from the packings")
        self.scalar_names = set(f["scalars"].keys())
        try:
            self.runs = json.loads(f.attrs.get("runs", "[]"))
        except (TypeError, ValueError):
            self.runs = []
        self.hosts = set()
        self.staged: dict[int, dict[int, tuple]] = {}   # block -> row -> (meta, arrays)
        self.staged_since: dict[int, float] = {}        # block -> when its first staged row came
        self.block_bytes: dict[int, int] = {}           # block -> bytes staged
        self.staged_bytes = 0
        self.in_journal: set[int] = set()               # rows with a record in the journal
        self.suspended_staged: dict[int, tuple] = {}     # row -> suspended packing's (meta, arrays)
        self.bad_checkpoints: set[str] = set()          # ids whose checkpoint was found damaged
        self.rounds_staged: dict[int, str] = {}         # ... and those in the journal only (JSON text)
        self.last_flush = time.monotonic()

    def _replay(self, records):
        """Stage the journal's records (a killed run's finished tasks, suspended packings, round
        decisions and runs): a row is a pure function of its last record, so replaying is idempotent."""
        for meta, arrays in records:
            if meta.get("type") == "task":
                self._stage(meta, arrays)
            elif meta.get("type") == "suspended":
                self._stage_suspended(meta, arrays)
            elif meta.get("type") == "round":
                self.rounds_staged[int(meta["round"])] = meta["record"]
            elif meta.get("type") == "run":
                self._merge_run(meta["run"])
            if self.staged_bytes > BUFFER_BYTES:
                self._write_blocks(list(self.staged))

    def _rerun_unrecorded_failures(self):
        """A row that says failed without its failure record (a SIGKILL tore the ``failures``
        group's index and took the link with it) is pending again: its task runs again and gets its
        record back, instead of a record rebuilt without its traceback."""
        lost = [int(i) for i in np.flatnonzero(self.status == FAILED) if self.tasks[i].id not in self.have_failures]
        if lost:
            self.status[lost] = PENDING
            self.log(f"campaign: {self.path}: {len(lost)} failed task(s) have lost their failure record; they "
                     "are pending again and will be run again")

    def n_final(self) -> int:
        return self.n_status[DONE] + self.n_status[FAILED]

    def _dataset_kwargs(self, shape, fill):
        return dataset_kwargs(self.B, shape, fill)

    @property
    def space_log(self):
        """(bytes reserved, bytes the file grew) of the last HDF5 write steps."""
        return self.space.log

    def _groups(self) -> int:
        """Configuration and failure groups the file holds."""
        return len(self.have_configs) + len(self.have_failures)

    # ---- recording
    def finished(self, index: int) -> bool:
        return self.status[index] != PENDING

    def record(self, index: int, summary: dict, attempts: int):
        """Record a task's final outcome: done if ``summary['ok']``, else failed."""
        meta, arrays = task_record(index, self.tasks[index].id, summary, attempts, self.edges, self.run["run_id"])
        self._append(meta, arrays)
        self._stage(meta, arrays)
        self.maybe_flush()

    def _append(self, meta, arrays):
        """A record into the journal (before anything touches the HDF5 file)."""
        size = self.journal.size
        try:
            self.journal.append(meta, arrays)
        except OutOfSpace:
            # the journal repeats what is staged for the store: writing the store and cutting the
            # journal back (a checkpoint) may free enough; if not (OutOfSpace again), the run stops
            if not (self.staged or self.in_journal or self.suspended_staged):
                raise
            self.checkpoint()
            size = self.journal.size
            self.journal.append(meta, arrays)
            self.log(f"campaign: {self.path.parent} was full: wrote the store and cut its journal back early, "
                     "which made room; going on")
        self.space.note_record(self.journal.size - size)

    # ---- a precision campaign's rounds (campaign.run.rounds)
    def record_round(self, record: dict):
        """Keep one round's decision (``campaign.precision.allocation.Decision.to_record``): into the
        journal first, then ``/precision/roundKKKK`` at the next flush. A round decided again (after a
        lost record) replaces its record."""
        text = json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False)
        meta = {"type": "round", "round": int(record["round"]), "record": text, "run_id": self.run["run_id"]}
        self._append(meta, {})
        self.rounds_staged[int(record["round"])] = text
        self.maybe_flush()

    def rounds(self) -> dict:
        """Every round's decision kept so far, ``{round: record}``."""
        out = dict(self.rounds_stored)
        out.update({k: json.loads(text) for k, text in self.rounds_staged.items()})
        return out

    def _write_rounds(self):
        rows = sorted(self.rounds_staged.items())
        need = sum(len(text) + 4096 for _, text in rows)
        with self.space.write_step(self.io, need, "writing the rounds' decisions into the store", len(self.scalar_names)):
            g = self.f.require_group(ROUNDS_GROUP)
            for k, text in rows:
                write_round(g, k, text)
                self.rounds_stored[k] = json.loads(text)
            self.f.flush()
        self.rounds_staged.clear()

    def columns(self, names) -> dict:
        """Whole per-task columns (``tasks/status``, ``scalars/A_G``, ...) as the store holds them once
        everything staged is written (a flush first); a scalar the store has no dataset for is NaN.
        For a precision campaign's decisions, read while the run goes on."""
        self.flush(force=True)
        out = {}
        for name in names:
            if name == "tasks/status":
                out[name] = self.status.copy()
            elif name not in self.f:
                out[name] = np.full(self.T, np.nan)
            else:
                out[name] = np.concatenate([self._read_block(name, lo, min(lo + self.B, self.T))
                                            for lo in range(0, self.T, self.B)]) if self.T else np.zeros(0)
        return out

    # ---- suspended packings (stop and go)
    def suspend(self, index: int, record: dict):
        """Keep the state of task ``index``'s packing, stopped at a step budget (a GPU worker's
        ``record``: ``arrays``, the four arrays of ``kernels.gpu.batch.Suspended.arrays``, and its
        counters ``steps``, ``force_evaluations``, ``device_seconds``, ``launches``). The task stays
        pending; the next dispatch of it resumes from this state (``suspended``)."""
        if self.status[index] != PENDING:
            return
        t = self.tasks[index]
        meta = {"type": "suspended", "index": int(index), "id": t.id, "run_id": self.run["run_id"]}
        meta.update({k: float(record[k]) if k == "device_seconds" else int(record[k]) for k in CHECKPOINT_ATTRS})
        arrays = {"k/" + k: np.ascontiguousarray(record["arrays"][k], np.float64) for k in CHECKPOINT_KEYS}
        self._append(meta, arrays)
        self._stage_suspended(meta, arrays)
        self.maybe_flush()

    def _stage_suspended(self, meta, arrays):
        i = int(meta["index"])
        if not (0 <= i < self.T) or self.tasks[i].id != meta["id"]:
            raise UserError(f"{str(self.journal.path)!r} does not match the spec (task {i})")
        if self.status[i] == DONE:
            return
        self.suspended_staged[i] = (meta, arrays)
        self.bad_checkpoints.discard(meta["id"])

    def has_suspended(self, index: int) -> bool:
        """Whether task ``index`` has a suspended packing kept (cheap: no read)."""
        return index in self.suspended_staged or self.tasks[index].id in self.have_checkpoints

    def suspended(self, index: int):
        """The arrays of task ``index``'s suspended packing (the four of ``CHECKPOINT_KEYS``), or
        None: it has none, or it cannot be read or does not match its checksum (then its task starts
        over, and the run says so once)."""
        got = self.suspended_staged.get(index)
        if got is not None:
            return {k: got[1]["k/" + k] for k in CHECKPOINT_KEYS}
        tid = self.tasks[index].id
        if tid not in self.have_checkpoints or tid in self.bad_checkpoints:
            return None
        arrays, _, problem = checkpoint_problem(self._checkpoint_group(tid))
        if problem is not None:
            self.bad_checkpoints.add(tid)
            self.log(f"campaign: {self.path}: the suspended packing of task {tid} (checkpoints/{tid}) {problem}; "
                     "the task starts over")
            return None
        return arrays

    def _checkpoint_group(self, tid):
        try:
            return self.f[f"checkpoints/{tid}"]
        except Exception:  # noqa: BLE001 - checkpoint_problem says it cannot be read
            return None

    def suspended_counts(self) -> dict:
        """Suspended packings kept: ``{"tasks", "steps"}`` (FIRE steps so far, summed)."""
        steps = 0
        n = 0
        for i, (meta, _) in self.suspended_staged.items():
            n += 1
            steps += int(meta["steps"])
        staged = {self.tasks[i].id for i in self.suspended_staged}
        for tid in self.have_checkpoints - staged - self.bad_checkpoints:
            try:
                steps += int(self.f[f"checkpoints/{tid}"].attrs["steps"])
                n += 1
            except Exception:  # noqa: BLE001 - not one we can resume
                pass
        return {"tasks": n, "steps": steps}

    def _write_checkpoints(self):
        """The staged suspended packings into ``/checkpoints`` (one write step), each replacing the
        task's earlier one."""
        rows = sorted(self.suspended_staged.items())
        need = sum(sum(a.nbytes for a in arrays.values()) + 6144 for _, (_, arrays) in rows)
        need += 96 * len(self.have_checkpoints)  # the group's name heap doubles when it fills
        with self.space.write_step(self.io, need, "writing suspended packings into the store", len(self.scalar_names)):
            g = self.f.require_group("checkpoints")
            for i, (meta, arrays) in rows:
                tid = self.tasks[i].id
                if tid in g:
                    del g[tid]
                write_checkpoint(g, tid, {k: arrays["k/" + k] for k in CHECKPOINT_KEYS},
                                 {k: meta[k] for k in CHECKPOINT_ATTRS})
                self.have_checkpoints.add(tid)
            self.f.flush()
        self.suspended_staged.clear()

    def _staged_row(self, index):
        return self.staged.get(index // self.B, {}).get(index)

    def configuration(self, index: int):
        """The stored configuration of task ``index`` (dict of arrays), or None."""
        row = self._staged_row(index)
        if row is not None:
            arrays = row[1]
            if "c/positions" in arrays:
                return {k: arrays["c/" + k] for k in ("positions", "radii", "box", "species")}
            return None
        tid = self.tasks[index].id
        if tid in self.have_configs:
            return self._stored_configuration(tid)
        return None

    def _stored_configuration(self, tid):
        """A configuration the store holds, checked against its checksum (StoreDamaged if not)."""
        try:
            g = self.f[f"configurations/{tid}"]
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise StoreDamaged(self._damaged(f"configurations/{tid}", f"cannot be read ({exc})")) from None
        try:
            return check_configuration(g, self.path, f"configurations/{tid}")
        except StoreDamaged as exc:
            raise StoreDamaged(self._damaged(f"configurations/{tid}", str(exc))) from None

    def _read_block(self, name, lo, hi):
        """Rows [lo, hi) of a block dataset this run adds rows to. A chunk that fails its checksum
        (or cannot be read) stops the run with StoreDamaged: it must not be written back."""
        try:
            data = self._dataset(name)[lo:hi]
            sums = self._sums_of(name)
            if sums is not None and lo // self.B not in self.unsure:
                check_rows(sums, name, lo, data, self.B)
            return data
        except BlockMismatch as exc:
            raise StoreDamaged(self._damaged(name, str(exc)[len(name) + 1:])) from None
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise StoreDamaged(self._damaged(name, f"rows {lo}-{hi - 1} cannot be read ({exc})")) from None

    def _damaged(self, name, how):
        how = how.split(". `campaign verify")[0]
        if how.startswith(f"{self.path} is damaged: "):
            how = how[len(f"{self.path} is damaged: "):]
        else:
            how = f"{name} {how}"
        return (f"{self.path} is damaged: {how}. This run met it while adding finished tasks to the store and "
                f"stopped; nothing it finished is lost (the journal {self.journal.path} keeps it). Run `campaign "
                f"verify {self.path} --repair` (it marks the tasks of the damaged part pending), then this command "
                "again: it replays the journal and recomputes those tasks")

    def read(self, column: str, index: int):
        """One value of a per-task dataset (``tasks/error``, ``scalars/phi``, ...), staged or stored."""
        row = self._staged_row(index)
        if row is not None:
            return row_values(row[0], row[1], self.edges, [column])[column]
        if column not in self.f:
            return np.nan if column.startswith("scalars/") else None
        return self.f[column][index]

    def _stage(self, meta, arrays):
        i = int(meta["index"])
        if not (0 <= i < self.T) or self.tasks[i].id != meta["id"]:
            raise UserError(f"{str(self.journal.path)!r} does not match the spec (task {i})")
        status = int(meta["status"])
        self.suspended_staged.pop(i, None)  # its suspended packing, if any, is removed with the row
        self.n_status[int(self.status[i])] -= 1
        self.n_status[status] += 1
        self.status[i] = status
        self.attempts[i] = meta["attempts"]
        self.wall[i] = meta["wall"]
        if meta.get("host") and int(meta.get("rank", -1)) >= 0:
            self.hosts.add(meta["host"])
        self.in_journal.add(i)
        b = i // self.B
        blk = self.staged.setdefault(b, {})
        if not blk:
            self.staged_since[b] = time.monotonic()
        old = blk.get(i)
        size = _nbytes(arrays) + 512 - (0 if old is None else _nbytes(old[1]) + 512)
        blk[i] = (meta, arrays)
        self.staged_bytes += size
        self.block_bytes[b] = self.block_bytes.get(b, 0) + size

    def _merge_run(self, run):
        for k, r in enumerate(self.runs):
            if r.get("run_id") == run.get("run_id"):
                self.runs[k] = run
                return
        self.runs.append(run)

    # ---- writing
    def _block_complete(self, b):
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        return not np.any(self.status[lo:hi] == PENDING)

    def maybe_flush(self):
        now = time.monotonic()
        if (self.staged_bytes > BUFFER_BYTES or self.journal.size > JOURNAL_BYTES
                or ((self.staged or self.suspended_staged or self.rounds_staged)
                    and now - self.last_flush >= FLUSH_SECONDS)):
            self.flush()

    def flush(self, force=False):
        """Write the staged blocks that are complete (all with ``force``, or when the buffer
        is full, the oldest first), then checkpoint if the journal has grown too long."""
        now = time.monotonic()
        if force:
            blocks = list(self.staged)
        else:
            blocks = [b for b in self.staged if self._block_complete(b) or now - self.staged_since[b] >= HOLD_SECONDS]
            if self.staged_bytes > BUFFER_BYTES:
                rest = sorted((b for b in self.staged if b not in set(blocks)), key=self.staged_since.get)
                size = self.staged_bytes - sum(self.block_bytes[b] for b in blocks)
                for b in rest:
                    if size <= BUFFER_BYTES // 2:
                        break
                    blocks.append(b)
                    size -= self.block_bytes[b]
        if blocks:
            self.journal.sync()  # the journal is durable before the store changes
            self._write_blocks(blocks)
        if self.suspended_staged:
            self.journal.sync()
            self._write_checkpoints()
        if self.rounds_staged:
            self.journal.sync()
            self._write_rounds()
        self.last_flush = time.monotonic()
        if self.journal.size > JOURNAL_BYTES:
            self.checkpoint()

    def _dataset(self, name):
        """The dataset ``name``, looked up once (h5py lookups are slow)."""
        got = self._datasets.get(name)
        if got is None:
            got = self._datasets[name] = self.f[name]
        return got

    def _sums_of(self, name):
        """The block checksums of the dataset ``name`` (None: a store without them)."""
        if self._sums is None:
            return None
        got = self._sums.get(name)
        if got is None:
            got = self._sums[name] = self.f.get(sums_name(name))
        return got

    def _write_blocks(self, blocks):
        """Data of the staged rows of ``blocks`` first, flush, then their status, flush.

        Rewriting a chunk that holds committed rows: a write cut by SIGKILL could take them
        with it, so each of them gets a record in the journal first (and the journal is made
        durable) before the HDF5 file is touched; then the space the writes may need is
        reserved, and only then does HDF5 write."""
        blocks = sorted(blocks)
        rejournalled = False
        for b in blocks:
            rows = self.staged[b]
            lo, hi = b * self.B, min((b + 1) * self.B, self.T)
            final = np.flatnonzero(self.status[lo:hi] != PENDING) + lo
            missing = [int(i) for i in final if i not in rows and i not in self.in_journal]
            if missing:
                self._rejournal(lo, hi, missing)
                rejournalled = True
        if rejournalled:
            self.journal.sync()
        need = self.space.blocks_bytes(self.staged, blocks, self.scalar_names, self._groups())
        what = "writing finished tasks into the store"
        with self.space.write_step(self.io, need, what, len(self.scalar_names), blocks):
            written = self._write_blocks_now(blocks)
        self.space.learn(written, blocks, self.scalar_names)

    def _write_blocks_now(self, blocks):
        """Write the staged rows of ``blocks`` (data, flush, status, flush); returns the per-task
        datasets written, by name."""
        f = self.f
        written = {}
        for b in blocks:
            rows = self.staged[b]
            lo, hi = b * self.B, min((b + 1) * self.B, self.T)
            final = np.flatnonzero(self.status[lo:hi] != PENDING) + lo
            whole = all(int(i) in rows for i in final)  # no committed row to keep: no need to read the chunks
            idx, values = block_values(rows, lo, self.edges)
            keys = set()
            for v in values:
                keys.update(v.keys())
            for name in sorted(k for k in keys if k.startswith("scalars/")):
                if name[8:] not in self.scalar_names:
                    f["scalars"].create_dataset(name[8:], dtype=np.float64, **self._dataset_kwargs((self.T,), np.nan))
                    if self._sums is not None:
                        create_fill_sums(f, name, self.T, self.B, (), np.float64, np.nan)
                    self.scalar_names.add(name[8:])
                    write_scalar_names(f["scalars"], self.scalar_names)
            columns = [f"tasks/{n}" for n in ROW_FIELDS] + [f"scalars/{n}" for n in sorted(self.scalar_names)]
            columns += [f"histograms/{h}/counts" for h in self.edges]
            for name in columns:
                ds = written[name] = self._dataset(name)
                kept = None if whole else self._read_block(name, lo, hi)
                block = column_block(name, hi - lo, idx, values, self.edges, kept)
                ds[lo:hi] = block
                write_sums(self._sums_of(name), lo, block, self.B)
            for i, (meta, arrays) in sorted(rows.items()):
                tid = self.tasks[i].id
                if "c/positions" in arrays:
                    if tid in self.have_configs:
                        del f[f"configurations/{tid}"]
                    write_configuration(f.require_group("configurations"), tid,
                                        {k: arrays["c/" + k] for k in CONFIG_KEYS})
                    self.have_configs.add(tid)
                if tid in self.have_failures:
                    del f[f"failures/{tid}"]
                    self.have_failures.discard(tid)
                if tid in self.have_checkpoints:  # finished: its suspended packing is of no more use
                    del f[f"checkpoints/{tid}"]
                    self.have_checkpoints.discard(tid)
                    self.bad_checkpoints.discard(tid)
                if int(meta["status"]) == FAILED:
                    write_failure(f["failures"], tid, {"message": meta["message"], "traceback": meta["traceback"],
                                                       "attempts": int(meta["attempts"]), "rank": int(meta["rank"]),
                                                       "host": meta["host"]})
                    self.have_failures.add(tid)
        f.flush()
        # ... then the commit marker
        status = self._dataset("tasks/status")
        for b in blocks:
            lo, hi = b * self.B, min((b + 1) * self.B, self.T)
            status[lo:hi] = self.status[lo:hi]
            write_sums(self._sums_of("tasks/status"), lo, self.status[lo:hi], self.B)
            self.staged.pop(b)
            self.staged_bytes -= self.block_bytes.pop(b)
            self.staged_since.pop(b, None)
        f.flush()
        if not self.staged:
            self.staged_bytes = 0
        return written

    def _rejournal(self, lo, hi, rows):
        """Append records, rebuilt from the store, for committed ``rows`` of block [lo, hi)."""
        f = self.f
        cols = {n: self._read_block(f"tasks/{n}", lo, hi) for n in ROW_FIELDS}
        scal = {n: self._read_block(f"scalars/{n}", lo, hi) for n in sorted(self.scalar_names)}
        hist = {h: self._read_block(f"histograms/{h}/counts", lo, hi) for h in self.edges}
        for i in rows:
            k, tid, status = i - lo, self.tasks[i].id, int(self.status[i])
            failure = f[f"failures/{tid}"].attrs if status != DONE and tid in self.have_failures else None
            conf = self._stored_configuration(tid) if tid in self.have_configs else None
            meta = {"type": "task", "index": i, "id": tid, "status": status,
                    "attempts": int(cols["attempts"][k]), "wall": float(cols["wall"][k]),
                    "rank": int(cols["rank"][k]), "host": cols["host"][k].decode(errors="replace"),
                    "message": cols["error"][k].decode(errors="replace"), "traceback": "", "run_id": None}
            arrays = {}
            if status == DONE:
                meta["scalars"] = {n: float(v[k]) for n, v in scal.items() if not np.isnan(v[k])}
                arrays = {"h/" + h: c[k] for h, c in hist.items()}
            elif failure is not None:
                meta["message"], meta["traceback"] = str(failure.get("message", "")), str(failure.get("traceback", ""))
            if conf is not None:
                arrays.update(("c/" + k, a) for k, a in conf.items())
            self.journal.append(meta, arrays)
            self.in_journal.add(i)
        self.journal.sync()

    def checkpoint(self):
        """Everything staged into the store, the store made durable, then the journal cut back
        to its header: from here on the store alone holds every finished task.

        A fault before the journal is cut (a full disk while writing the staged rows, an
        ``fsync`` that fails) leaves the journal whole: it still holds everything."""
        if self.staged:
            self.journal.sync()
            self._write_blocks(list(self.staged))
        if self.suspended_staged:
            self.journal.sync()
            self._write_checkpoints()
        if self.rounds_staged:
            self.journal.sync()
            self._write_rounds()
        with self.space.write_step(self.io, 0, "flushing the store at a checkpoint", len(self.scalar_names)):
            self.f.flush()
        try:
            fsync_path(self.path)
        except OSError as exc:
            fault = write_fault(exc, self.path, "making the store durable (fsync) at a checkpoint")
            if fault is None:
                raise
            raise fault from None
        self.journal.cut_back(self.spec.hash, self.T, self.runs, self.n_final(), _now())
        self.in_journal = set()
        self.last_flush = time.monotonic()

    def _write_root_attrs(self):
        run = self.run
        attrs = {"schema": SCHEMA, "format_version": FORMAT_VERSION, "name": self.spec.name,
                 "spec_hash": self.spec.hash, "spec_yaml": self.spec.text}
        for key in ("package_version", "git_commit"):
            attrs[key] = str(run.get(key, "unknown"))
        attrs["versions"] = json.dumps(run.get("versions", {}), sort_keys=True)
        attrs["runs"] = json.dumps(self.runs, sort_keys=True)
        hosts = sorted({h for r in self.runs for h in r.get("hosts", [])})
        attrs["hosts"] = json.dumps(hosts)
        attrs["start_time"] = self.runs[0].get("start") or ""
        attrs["end_time"] = self.runs[-1].get("end") or ""
        with self.space.write_step(self.io, self.space.attrs_bytes(attrs), "writing the store's attributes",
                             len(self.scalar_names)):
            for key, value in attrs.items():
                self.f.attrs[key] = value

    def close(self, **end_info):
        """Write everything, stamp the run's end (``end_info``, the end time and the master's
        peak memory), checkpoint, release the lock.

        A WriteFault on the way (a full disk) leaves the store and its journal consistent
        (the journal holds whatever the store could not take) and the file closed."""
        if self.f is None:
            return
        ok = False
        try:
            self.run.update(end_info, end=_now(), master_peak_rss_mb=peak_rss_mb())
            self.run["hosts"] = sorted(set(self.run.get("hosts", [])) | self.hosts)
            self.journal.append({"type": "run", "run": self.run})
            self._merge_run(self.run)
            self.flush(force=True)
            self._write_root_attrs()
            self.checkpoint()
            ok = True
        finally:
            if ok:
                self.f.close()  # writes nothing: the checkpoint flushed everything
                self.f = None
                self.io.close()
                self.journal.close()
            else:
                self.abandon()

    def abandon(self):
        """Close without stamping the run's end (after a fault); the journal stays the record.

        A poisoned handle (a write step failed) closes without writing anything more: its
        writes go to an in-memory overlay, so that the file on disk keeps what it had."""
        try:
            if self.f is not None:
                if self.io.poisoned:
                    self.io.discard()
                try:
                    self.f.close()
                except Exception:  # noqa: BLE001 - after a fault: what the file holds is what the next start sees
                    if not self.io.poisoned:
                        raise
        finally:
            self.f = None
            if getattr(self, "io", None) is not None:
                self.io.close()
            if getattr(self, "journal", None) is not None:
                try:
                    self.journal.close()  # closes its descriptor (the lock) even when the sync fails
                except Exception:  # noqa: BLE001 - what the journal holds is what the next start sees
                    pass

    def counts_by_status(self):
        return {"pending": self.n_status[PENDING], "done": self.n_status[DONE], "failed": self.n_status[FAILED]}

    def space_needed(self) -> dict:
        """What finishing the campaign would take on disk, from what this store holds:
        ``{"per_task", "journal_per_task", "pending", "total"}`` (bytes; None when unknown;
        ``StoreSpace.needed``)."""
        return self.space.needed(pending=self.n_status[PENDING], final=self.n_final(), staged=self.staged,
                                 scalar_names=self.scalar_names, groups=self._groups(), journal_cap=JOURNAL_BYTES)


def _nbytes(arrays) -> int:
    return sum(a.nbytes for a in arrays.values()) if arrays else 0


def _make_directory(path):
    """The directory the store ``path`` goes into, made if missing (a full disk: OutOfSpace; any other
    refusal: UserError, before anything is written)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fault = write_fault(exc, path.parent, "creating the output directory")
        if fault is not None and fault.out_of_space:
            raise fault from None
        raise UserError(f"cannot create the directory of {str(path)!r}: {exc.strerror or exc}") from None


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")
