"""One task in, one summary out; and the loop a worker process runs.

The per-task work is a *task function* chosen by name in the run context:

* ``"kernels"`` (the default): ``kernels.jam`` then ``kernels.analyze``.
* ``"synthetic"``: a cheap deterministic stand-in (scalars and histograms drawn
  from the task's seed), used by the engine's tests and benchmarks so they do
  not depend on numba. Environment variables make it misbehave on purpose:
  ``CAMPAIGN_SYNTHETIC_DELAY`` (seconds per task, times N/64 if it ends in
  ``*N``), ``CAMPAIGN_SYNTHETIC_FAIL`` (tasks that always raise),
  ``CAMPAIGN_SYNTHETIC_FLAKY`` (tasks that raise on their first attempt only),
  ``CAMPAIGN_SYNTHETIC_CRASH`` (tasks that kill their worker process). Each is a
  comma-separated list of ``seed:K`` (seed index K), ``N:K`` or task-id prefixes.
  ``CAMPAIGN_SYNTHETIC_STEPS="SECONDS:STEPS"`` makes a GPU worker's ``device: gpu`` task a search
  of ``STEPS x (1 + seed % 3)`` steps of ``SECONDS`` each (slept, one packing after the other, as
  the block's emulation runs them) that stops at a launch's step budget and goes on from its
  state (``SyntheticState``): the stop and go of ``campaign.run.gpuworker`` without the kernels.
  Its scalar ``search_end`` is where the search ended, which depends on every bit of the state it
  went on from.
* ``"package.module:attribute"``: any object with ``run(payload, context)``
  and ``histogram_edges(context)`` (and optionally ``warm_up(context)``).

Workers never raise: ``run_task`` returns the contract's summary dict with
``ok=False`` and an error record (message, traceback) when anything fails.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import signal
import socket
import time
import traceback

import numpy as np

JAM_STATUS = {"converged": 0, "max_search": 1, "max_steps": 2}
_HOST = socket.gethostname()


# --------------------------------------------------------------------------- task functions

class KernelTask:
    """The real work: ``kernels.jam`` then ``kernels.analyze`` (docs/CONTRACTS.md)."""

    def histogram_edges(self, context) -> dict:
        from campaign.plan.spec import histogram_edges

        return histogram_edges(context["histograms"], context.get("bins"))

    def warm_up(self, context) -> None:
        """Compile (or load from the numba cache) every kernel a task will use: one small packing
        per protocol of ``context["protocol_warmups"]`` (the engine's list of distinct choices).
        With ``context["warm_helper"]`` (a local run's master on several cores) and a cold cache,
        a second process compiles the analysis while this one compiles the search
        (``_warm_analysis``); this one then loads the analysis from the cache."""
        helper = _start_analysis_helper(context) if context.get("warm_helper") else None
        for protocol in context.get("protocol_warmups") or [{}]:
            if protocol.get("device") == "gpu":
                from kernels.gpu import simulated

                if simulated():  # numba's CUDA simulator compiles nothing (and is slow)
                    continue
            payload = {"N": 16, "E": 1e-3, "entropy": [0], "protocol": protocol}
            if helper is not None:
                helper = self._warm_beside(helper, payload, context)
            else:
                self.run(payload, context)
        if helper is not None:
            helper.join()

    def _warm_beside(self, helper, payload, context):
        """The search's kernels here while ``helper`` compiles the analysis; then, once it has
        finished, the analysis loaded from the cache. Returns None (the helper is done)."""
        got = self._jam(payload, context)
        helper.join()
        self._analyse(payload, context, *got)
        return None

    def run(self, payload, context):
        return self._analyse(payload, context, *self._jam(payload, context))

    def _setup(self, payload, context):
        """The variant's system (a spec's variants may override it, else the spec's), its exponent
        and the ``kernels.jam`` keywords of the task's protocol."""
        system = (context.get("systems") or {}).get(payload.get("variant"), context["system"])
        exponent = system["potential"]["exponent"]
        protocol = dict(payload["protocol"])
        if "sizes" in system:
            protocol["sizes"] = (system["sizes"]["distribution"], system["sizes"]["polydispersity"])
        else:
            protocol["species"] = tuple((f, r) for _, f, r in system["species"])
        protocol.pop("start", None)  # "ladder": the master sends the parent's packing as payload["start"]
        return system, exponent, protocol

    def _jam(self, payload, context):
        import kernels

        system, exponent, protocol = self._setup(payload, context)
        if protocol.get("device") == "gpu":
            got = self.jam_batch([payload], context)[0]
            if isinstance(got, Exception):
                raise got
            return got
        start = payload.get("start")
        if start is not None:
            start = (start["positions"], start["radii"], start["species"], start["box"])
        t0 = time.perf_counter()
        p = kernels.jam(payload["N"], payload["E"], list(payload["entropy"]), start=start,
                        box=tuple(system["box"]), exponent=exponent, **protocol)
        return p, time.perf_counter() - t0

    def jam_batch(self, payloads, context):
        """``device: gpu`` tasks of one variant and N, each in its own thread block of one launch
        (``kernels.gpu.jam_batch``: on this worker's GPU, else the block's CPU emulation). Returns
        ``(packing, seconds)`` per task (the batch's time shared equally), or the exception that
        failed it."""
        return self.finish_batch(self.start_batch(payloads, context))

    def start_batch(self, payloads, context, budget=None, resume=None):
        """Launch ``jam_batch``'s packings (on a GPU it returns at once): the handle of
        ``finish_batch`` (``campaign.run.gpuworker``). ``budget``: FIRE steps each packing may take
        in this launch (None: unbounded); ``resume``: per task None or the ``Suspended`` packing it
        goes on from; a task without one goes on from its payload's ``resume`` (the arrays of a
        packing the store kept suspended), if it has one."""
        from kernels.gpu.batch import Suspended, start_batch

        system, exponent, protocol = self._setup(payloads[0], context)
        protocol.pop("device")
        protocol.pop("gpu_block", None)  # (the block's version: its identity, not a setting)
        threads = protocol.pop("gpu_threads", None)
        resume = list(resume) if resume is not None else [None] * len(payloads)
        for k, p in enumerate(payloads):
            if resume[k] is None and p.get("resume") is not None:
                resume[k] = Suspended.from_arrays(p["resume"], p["E"])
        t0 = time.perf_counter()
        handle = start_batch(payloads[0]["N"], [p["E"] for p in payloads],
                             [list(p["entropy"]) for p in payloads], threads=threads, budget=budget,
                             resume=resume if any(r is not None for r in resume) else None,
                             box=tuple(system["box"]), exponent=exponent, **protocol)
        return handle, t0, len(payloads)

    def batch_done(self, started) -> bool:
        """Whether a launch of ``start_batch`` has ended (never waits)."""
        from kernels.gpu.batch import batch_done

        return batch_done(started[0])

    def slots(self, started) -> int:
        """Blocks the device holds at once for a launch of ``start_batch`` (its occupancy)."""
        from kernels.gpu.batch import occupancy

        return int(occupancy(started[0])["slots"])

    def clock(self, item):
        """Block-seconds and FIRE steps (force evaluations for a finished packing: one per step
        but for a few) of a launch's item: what ``campaign.run.gpuworker.StepBudget`` learns from."""
        if hasattr(item, "arrays"):  # suspended
            return float(item.device_clock["seconds"]), float(item.steps)
        p = item[0]
        return float(p.settings["device_clock"]["seconds"]), float(p.force_evaluations)

    def finish_batch(self, started):
        """Collect a batch ``start_batch`` launched (waiting for it to end): ``(packing, seconds)``
        per task, a ``Suspended`` packing that reached the launch's budget, or the exception that
        failed it. Every packing's device clock gets the launch's resident slots (``slots``)."""
        from kernels.gpu.batch import finish_batch

        handle, t0, n = started
        out = finish_batch(handle)
        share = (time.perf_counter() - t0) / n
        slots = self.slots(started)
        got = []
        for p in out:
            if isinstance(p, Exception) or hasattr(p, "arrays"):
                got.append(p)
                continue
            clock = p.settings.get("device_clock")
            if clock is not None:
                clock["slots"] = slots
            got.append((p, share))
        return got

    def run_batch(self, payloads, context):
        """``run`` for a batch of ``device: gpu`` tasks (``batch_key`` equal): one launch, then
        each packing analysed. Returns per task ``run``'s tuple or the exception that failed it."""
        out = []
        for payload, got in zip(payloads, self.jam_batch(payloads, context)):
            if isinstance(got, Exception):
                out.append(got)
                continue
            try:
                out.append(self.analyse(payload, context, *got))
            except Exception as exc:  # noqa: BLE001 - that task fails, the batch goes on
                out.append(exc)
        return out

    def analyse(self, payload, context, p, jam_seconds):
        """The summary tuple of ``run`` for the packing ``p`` made in ``jam_seconds``."""
        return self._analyse(payload, context, p, jam_seconds)

    def _analyse(self, payload, context, p, jam_seconds):
        import kernels

        system, exponent, protocol = self._setup(payload, context)
        t1 = time.perf_counter()
        obs = [o for o in context["observables"]]
        bins = {h: np.asarray(e, dtype=np.float64) for h, e in (context.get("edges") or {}).items()}
        # the isostatic count of the cell (2 N_G - 1 fixed, 2 N_G + 1 shear-stabilised): z_iso, delta_Z
        cell = {"cell": protocol["cell"]} if "cell" in protocol else {}
        a = kernels.analyze(p.positions, p.radii, p.box, observables=obs, bins=bins or None,
                            exponent=exponent, species=p.species, **cell)
        t2 = time.perf_counter()
        scalars = {k: float(v) for k, v in a.scalars.items()}
        # each identity flag too (1.0 holds), so a campaign shows which identity a packing fails
        scalars.update({f"identity_{k}": float(bool(v)) for k, v in a.identities.items()})
        scalars.update(force_residual=float(p.force_residual), iterations=float(p.iterations),
                       force_evaluations=float(p.force_evaluations),
                       jam_status=float(getattr(p, "status_code", JAM_STATUS.get(str(p.status), 9))),
                       sigma_max=float(np.max(p.radii)), jam_seconds=jam_seconds, analyze_seconds=t2 - t1)
        if protocol.get("endgame", "none") != "none":
            scalars["factorizations"] = float(p.factorizations)  # the Newton endgame's sparse Cholesky
        for name in ("energy_nonrattler", "pressure", "phi"):
            if name not in scalars and hasattr(p, name):
                scalars[name] = float(getattr(p, name))
        hists = {h: a.histograms[h] for h in context["histograms"]}
        config = None
        if context.get("configurations") or payload.get("return_configuration"):
            config = {"positions": np.asarray(p.positions, np.float64), "radii": np.asarray(p.radii, np.float64),
                      "box": np.asarray(p.box, np.float64), "species": np.asarray(p.species, np.int32)}
        settings = getattr(p, "settings", {})
        clock = settings.get("device_clock")
        if clock is not None:  # a GPU packing's device clock (docs/STORE.md: the busy fraction)
            scalars.update(device_start=float(clock["start"]), device_end=float(clock["end"]),
                           device_seconds=float(clock["seconds"]), device_launches=float(clock["launches"]),
                           device_slots=float(clock.get("slots", np.nan)))
        device = settings.get("device")
        if device:  # a GPU packing: what ran it, recorded beside the host
            return scalars, hists, config, device
        return scalars, hists, config


def _analysis_cached() -> bool:
    """Whether numba's cache already holds the analysis (its rotation kernel, which only the
    analysis calls, has an index file); True where that cannot be told (then no helper)."""
    try:
        from kernels.network import _rotation_core

        return os.path.exists(_rotation_core._cache._cache_file._index_path)
    except Exception:  # noqa: BLE001 - numba's internals differ: compile in one process, as before
        return True


def _start_analysis_helper(context):
    """A process compiling the analysis of the tasks' observables into the numba cache
    (``_warm_analysis``), or None when the cache has it already or this machine has one core."""
    if (os.cpu_count() or 1) < 2 or _analysis_cached():
        return None
    import multiprocessing

    helper = multiprocessing.get_context("spawn").Process(target=_warm_analysis, args=(context,), daemon=True)
    helper.start()
    return helper


def stand_in():
    """16 disks in a unit box with contacts, voids, fictitious contacts and rattlers (a jittered
    lattice of offset rows, overlaps up to 15%), with the types of a packing of ``kernels.jam``
    (a task's box, its size or a tilted cell's, is also a float64 vector): what
    ``_warm_analysis`` analyses."""
    from types import SimpleNamespace

    box = np.ones(2)
    rng = np.random.default_rng(0)
    j, i = np.divmod(np.arange(16), 4)
    frac = np.stack([(i + 0.5 * (j % 2)) / 4.0, j / 4.0], axis=1) + 0.01 * rng.standard_normal((16, 2))
    positions = np.ascontiguousarray((frac % 1.0) * box)
    radii = 0.5 * 1.15 * np.sqrt(box[0] * box[1]) / 4.0 * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, 16))
    return SimpleNamespace(positions=positions, radii=radii, box=box, species=np.zeros(16, dtype=np.int32),
                           force_residual=0.0, iterations=0, force_evaluations=0, status="converged",
                           status_code=0, factorizations=0)


def _warm_analysis(context, quiet=True):
    """Compile what ``KernelTask._analyse`` calls for the tasks' observables, bins and (first)
    system, on ``stand_in``'s configuration. In the helper process (``quiet``) a failure only
    leaves the master to compile what is missing."""
    protocols = context.get("protocol_warmups") or [{}]
    payload = {"N": 16, "E": 1e-3, "entropy": [0], "protocol": protocols[0]}
    task = KernelTask()
    try:
        return task._analyse(payload, context, stand_in(), 0.0)
    except Exception:  # noqa: BLE001 - see above
        if not quiet:
            raise
        return None


def visible_device(k: int) -> str:
    """``CUDA_VISIBLE_DEVICES`` for a worker's ``k``-th GPU: the k-th (cyclically) of the devices
    the process may already see (SLURM lists the node's GPUs of the job, or the one it bound the
    rank to), else GPU ``k`` of the node."""
    seen = [d for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    return seen[k % len(seen)].strip() if seen else str(k)


def batch_key(payload):
    """Tasks that can share one GPU launch have equal keys (a ``device: gpu`` task: its variant, N
    and protocol; energies and seeds may differ); None for a task that runs alone."""
    proto = payload.get("protocol") or {}
    if proto.get("device") != "gpu" or payload.get("start") is not None:
        return None
    return payload.get("variant"), payload["N"], tuple(sorted(proto.items()))


def _matches(spec: str, payload) -> bool:
    for item in filter(None, (s.strip() for s in spec.split(","))):
        if item.startswith("seed:") and payload["seed"] == int(item[5:]):
            return True
        if item.startswith("N:") and payload["N"] == int(item[2:]):
            return True
        if ":" not in item and payload["id"].startswith(item):
            return True
    return False


#: Bins per histogram of kernels.analysis.DEFAULT_BINS (tests/storage/test_store.py checks they agree);
#: written out so that the synthetic task does not import numba.
SYNTHETIC_BINS = {"contact_angle": 180, "contact_length": 160, "z_g": 21, "z_v": 41, "alpha_e": 200,
                  "alpha_v": 400, "fictitious_length": 300, "radial_grains": 400, "radial_contacts": 300}


class SyntheticTask:
    """A deterministic stand-in for the kernels: a pure function of the task payload."""

    SCALARS = ("N", "N_G", "N_R", "E_G", "phi", "pressure", "A_G", "A_V", "N_C", "N_V", "N_F",
               "z_g_mean", "z_iso", "delta_Z", "psi_O", "psi_DO", "identities_ok", "force_residual",
               "iterations", "force_evaluations", "jam_status", "sigma_max", "ordered_fraction")

    def histogram_edges(self, context) -> dict:
        """The spec's bins, else as many bins as the kernels' defaults (so that the engine's
        tests and benchmarks move as much data per task as real campaigns do)."""
        bins = context.get("bins") or {}
        out = {}
        for h in context["histograms"]:
            if h in bins:
                out[h] = np.asarray(bins[h], np.float64)
            else:
                out[h] = np.linspace(0.0, 1.0, SYNTHETIC_BINS.get(h, 10) + 1)
        return out

    def run_batch(self, payloads, context):
        """``run`` per task (the engine's tests of GPU batches), recording the batch's size."""
        return [got if isinstance(got, Exception) else self.analyse(p, context, *got)
                for p, got in zip(payloads, self.finish_batch(self.start_batch(payloads, context)))]

    # a GPU worker's event loop (campaign.run.gpuworker): the "packing" is the task's own outcome
    def start_batch(self, payloads, context, budget=None, resume=None):
        stepping = _synthetic_steps()
        resume = resume or [None] * len(payloads)
        out = []
        for p, state in zip(payloads, resume):
            try:
                launches = None
                if stepping is not None and (p.get("protocol") or {}).get("device") == "gpu":
                    if state is None and p.get("resume") is not None:
                        state = SyntheticState.from_arrays(p["resume"], p)
                    got = _synthetic_search(p, state, budget, *stepping)
                    if isinstance(got, SyntheticState):
                        out.append(got)
                        continue
                    launches, end = got
                    scalars, hists, config = self.run(p, context)
                    out.append(((dict(scalars, search_end=end), hists, config), float(len(payloads)), launches))
                    continue
                out.append((self.run(p, context), float(len(payloads)), launches))
            except Exception as exc:  # noqa: BLE001 - that task fails, the batch goes on
                out.append(exc)
        return out

    def finish_batch(self, started):
        return started

    def slots(self, started):
        return 1  # one packing after the other

    def clock(self, item):
        if isinstance(item, SyntheticState):
            return item.device_clock["seconds"], float(item.steps)
        return float("nan"), float("nan")

    def analyse(self, payload, context, got, size, launches=None):
        scalars, hists, config = got
        scalars = dict(scalars, batch_size=size)
        if launches is not None:
            scalars["device_launches"] = float(launches)
        return scalars, hists, config

    def run(self, payload, context):
        env = os.environ
        attempt = payload.get("attempt", 1)
        delay = env.get("CAMPAIGN_SYNTHETIC_DELAY", "")
        if delay:
            seconds = float(delay[:-2]) * payload["N"] / 64 if delay.endswith("*N") else float(delay)
            time.sleep(seconds)
        if _matches(env.get("CAMPAIGN_SYNTHETIC_CRASH", ""), payload):
            os._exit(3)
        if _matches(env.get("CAMPAIGN_SYNTHETIC_FAIL", ""), payload):
            raise RuntimeError(f"synthetic failure of task {payload['id']} (seed {payload['seed']})")
        if attempt == 1 and _matches(env.get("CAMPAIGN_SYNTHETIC_FLAKY", ""), payload):
            raise RuntimeError(f"synthetic first-attempt failure of task {payload['id']}")
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(list(payload["entropy"]))))
        N, E = payload["N"], payload["E"]
        tol = float(payload["protocol"].get("force_tolerance", 1e-6))
        window = float(payload["protocol"].get("window", 0.1))
        u = rng.random(len(self.SCALARS))
        scalars = {name: float(x) for name, x in zip(self.SCALARS, u)}
        scalars.update(N=float(N), E_G=E * (1 + window * u[3]), force_residual=tol * u[17], identities_ok=1.0,
                       jam_status=0.0)
        hists = {}
        for h, edges in (context.get("edges") or {}).items():
            k = len(edges) - 1
            hists[h] = rng.multinomial(N, np.full(k, 1.0 / k)).astype(np.int64)
        if payload.get("start") is not None:
            # a ladder step: show which configuration it started from
            scalars["start_checksum"] = float(np.sum(payload["start"]["positions"]))
        stepping = _synthetic_steps()
        if stepping is not None and (payload.get("protocol") or {}).get("device") == "gpu":
            # where its search ends when it runs in one go (a GPU worker's stop and go: start_batch)
            start, stride = _synthetic_walk(payload)
            scalars["search_end"] = _synthetic_end(start + stride * np.uint64(_synthetic_need(payload, stepping[1])))
        config = None
        if context.get("configurations") or payload.get("return_configuration"):
            pos = rng.random((N, 2))
            config = {"positions": pos, "radii": np.where(np.arange(N) < N // 2, 1.4, 1.0) * 0.01,
                      "box": np.array([1.0, 1.0]), "species": (np.arange(N) >= N // 2).astype(np.int32)}
        return scalars, hists, config


#: the known laws of ``SyntheticLawsTask`` (docs/PRECISION.md's checks): A_G and psi_O against E_G and
#: Delta Z, with finite-size corrections and a spread between packings falling like 1/sqrt(N)
SYNTHETIC_LAWS = {"A_inf": 0.446, "a_N": -0.6, "a_N2": 0.0, "c_A": 0.5, "beta_A": 0.28, "sigma_A": 0.08,
                  "P_inf": 0.369, "p_N": -0.4, "c_P": 0.6, "beta_P": 0.27, "sigma_P": 0.12,
                  "c_Z": 3.0, "sigma_Z": 0.3, "fe0": 400.0}


def synthetic_laws(N, E, entropy, laws=None) -> dict:
    """The scalars of a synthetic packing that follows known laws (``SYNTHETIC_LAWS``), a pure function
    of (N, E, the task's seed entropy): ``E_G`` in [E, 1.1 E]; ``delta_Z = c_Z E_G^(1/4) (1 + noise)``;
    ``A_G = A_inf + a_N / N + a_N2 / N^2 + c_A E_G^beta_A + noise / sqrt(N)``, ``psi_O`` alike without
    the ``1/N^2`` term (so ``beta_E`` and ``psi_beta_E`` are known, and ``beta_Z = 4 beta_A``); ``force_evaluations`` growing with N and with
    every decade closer to jamming, as the kernels' do."""
    t = dict(SYNTHETIC_LAWS, **(laws or {}))
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(list(entropy) + [7])))
    u = rng.random()
    z = rng.standard_normal(3)
    e = E * (1.0 + 0.1 * u)
    dz = t["c_Z"] * e ** 0.25 * max(0.0, 1.0 + t["sigma_Z"] * z[0])
    decades = max(0.0, math.log10(1e-3 / E))
    return {"E_G": e, "delta_Z": dz,
            "A_G": t["A_inf"] + t["a_N"] / N + t["a_N2"] / N ** 2 + t["c_A"] * e ** t["beta_A"] + t["sigma_A"] * z[1] / math.sqrt(N),
            "psi_O": t["P_inf"] + t["p_N"] / N + t["c_P"] * e ** t["beta_P"] + t["sigma_P"] * z[2] / math.sqrt(N),
            "force_evaluations": float(int(t["fe0"] * (1.0 + decades) ** 1.5 * (N / 64.0) ** 0.5
                                           * (1.0 + 0.3 * rng.random())))}


class SyntheticLawsTask(SyntheticTask):
    """``SyntheticTask`` whose physical scalars follow known laws (``synthetic_laws``): campaigns that
    fit, extrapolate and decide rounds on them run in seconds, with a truth to compare with. Its
    laws can be changed for a test with ``CAMPAIGN_SYNTHETIC_LAWS`` (JSON, keys of ``SYNTHETIC_LAWS``)."""

    def run(self, payload, context):
        scalars, hists, config = super().run(payload, context)
        laws = json.loads(os.environ.get("CAMPAIGN_SYNTHETIC_LAWS", "") or "{}")
        scalars.update(synthetic_laws(int(payload["N"]), float(payload["E"]), payload["entropy"], laws))
        return scalars, hists, config


def _synthetic_steps():
    """``CAMPAIGN_SYNTHETIC_STEPS`` as (seconds per step, steps), or None."""
    text = os.environ.get("CAMPAIGN_SYNTHETIC_STEPS", "")
    if not text:
        return None
    seconds, steps = text.split(":")
    return float(seconds), int(steps)


def _synthetic_need(payload, steps):
    """The steps of a task's synthetic search: ``steps`` times 1, 2 or 3 (by its seed)."""
    return steps * (1 + int(payload["seed"]) % 3)


def _synthetic_walk(payload):
    """A synthetic search's walk: one uint64 word per coordinate of its N disks, from ``start``,
    each step adding ``stride`` (mod 2^64; both the task's own). Multiples of 2^11 (53 significant
    bits): a float64 position ``word / 2^64`` holds each exactly."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(list(payload["entropy"]) + [1])))
    shape = (int(payload["N"]), 2)
    start = rng.integers(0, 2**53, shape, dtype=np.uint64) << np.uint64(11)
    stride = (rng.integers(0, 2**52, shape, dtype=np.uint64) * np.uint64(2) + np.uint64(1)) << np.uint64(11)
    return start, stride


def _synthetic_end(words) -> float:
    """Where a synthetic search ended (its ``search_end``): the CRC-32 of its walk's last words."""
    import zlib

    return float(zlib.crc32(np.ascontiguousarray(words).tobytes()))


def _synthetic_search(payload, state, budget, seconds, steps):
    """Run a synthetic search (``CAMPAIGN_SYNTHETIC_STEPS``) on from ``state`` (its walk's words, None: the
    task's start) for at most ``budget`` steps: ``(launches, search_end)`` when it ends, else the
    ``SyntheticState`` it stopped in."""
    need = _synthetic_need(payload, steps)
    start, stride = _synthetic_walk(payload)
    done, launches, words = (0, 1, start) if state is None else (state.steps, state.launches + 1, state.words)
    run = need - done if budget is None else min(need - done, int(budget))
    time.sleep(run * seconds)
    words = words + stride * np.uint64(run)
    if done + run < need:
        return SyntheticState(payload, done + run, launches, seconds, words)
    return launches, _synthetic_end(words)


class SyntheticState:
    """A synthetic search stopped at a step budget, shaped as ``kernels.gpu.batch.Suspended``: its
    walk's words as the positions of its N disks (arrays as large as a packing's) and its counters.
    The search goes on from whatever words and steps its arrays hold, so that a task that goes on
    from other bits than those it stopped with ends with another ``search_end`` than a search run
    in one go."""

    def __init__(self, payload, steps, launches, seconds, words):
        self.payload, self.steps, self.launches, self.seconds = payload, int(steps), int(launches), seconds
        self.words = words
        self.force_evaluations = self.steps
        self.device_clock = {"seconds": self.steps * seconds, "launches": self.launches}

    def arrays(self):
        pos = self.words.astype(np.float64) * 2.0**-64  # exact: 53 significant bits
        return {"positions": pos, "velocities": pos.T * 0.5, "reference": pos.T.copy(),
                "state": np.array([self.steps, self.launches, self.seconds], np.float64)}

    @classmethod
    def from_arrays(cls, arrays, payload):
        steps, launches, seconds = (float(x) for x in arrays["state"][:3])
        words = (np.asarray(arrays["positions"], np.float64) * 2.0**64).astype(np.uint64)
        return cls(payload, int(steps), int(launches), seconds, words)


def resolve(name: str):
    """The task function object for a name from the run context."""
    if name in ("kernels", None, ""):
        return KernelTask()
    if name == "synthetic":
        return SyntheticTask()
    if name == "synthetic-laws":
        return SyntheticLawsTask()
    module, _, attr = name.partition(":")
    obj = getattr(importlib.import_module(module), attr)
    return obj() if isinstance(obj, type) else obj


# --------------------------------------------------------------------------- one task

def run_task(fn, payload: dict, context: dict, rank: int = 0) -> dict:
    """Run one task; never raises. Returns the summary dict of docs/CONTRACTS.md."""
    t0 = time.perf_counter()
    try:
        got = fn.run(payload, context)
    except Exception as exc:  # noqa: BLE001 - a worker reports, it never raises
        got = exc
    return _summary(payload, context, rank, got, time.perf_counter() - t0)


def run_tasks(fn, payloads: list, context: dict, rank: int = 0) -> list:
    """Run a batch of tasks of one ``batch_key`` in one call of ``fn.run_batch``; never raises.
    A fault of the whole batch (a GPU error: out of memory, a lost device) fails every task of
    it with that reason. Returns one summary per task; ``wall`` is the batch's time shared."""
    t0 = time.perf_counter()
    try:
        got = fn.run_batch(payloads, context)
    except Exception as exc:  # noqa: BLE001 - a worker reports, it never raises
        got = [exc] * len(payloads)
    wall = (time.perf_counter() - t0) / len(payloads)
    return [_summary(p, context, rank, g, wall) for p, g in zip(payloads, got)]


def _summary(payload, context, rank, got, wall):
    """The summary of one task from what its task function returned, or the exception (with its
    traceback) that failed it."""
    summary = {"id": payload["id"], "ok": False, "scalars": {}, "histograms": {}, "configuration": None,
               "wall": wall, "rank": rank, "host": _HOST, "error": None}
    try:
        if isinstance(got, Exception):
            raise got
        scalars, hists, config, *device = got
        if device:  # the task function says what ran it (a GPU packing): the store's host column
            summary["host"] = f"{_HOST} {device[0]}"
        edges = context.get("edges") or {}
        if set(hists) != set(edges):
            raise RuntimeError(f"the task returned histograms {sorted(hists)}, expected {sorted(edges)}")
        for h, counts in hists.items():
            counts = np.asarray(counts)
            if counts.shape != (len(edges[h]) - 1,):
                raise RuntimeError(f"histogram {h!r} has shape {counts.shape}, expected ({len(edges[h]) - 1},) "
                                   "from its bin edges")
            hists[h] = counts.astype(np.int64, copy=False)
        summary.update(ok=True, scalars={k: float(v) for k, v in scalars.items()}, histograms=hists,
                       configuration=config)
    except Exception as exc:  # noqa: BLE001 - a worker reports, it never raises
        summary.update(ok=False, scalars={}, histograms={}, configuration=None,
                       error={"message": f"{type(exc).__name__}: {exc}"[:2000],
                              "traceback": "".join(traceback.format_exception(exc))[-20000:]})
    return summary


# --------------------------------------------------------------------------- dying with the master

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _parent_death_signal(sig=signal.SIGKILL) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies (prctl PR_SET_PDEATHSIG):
    the kernel delivers it even while a compiled kernel holds the interpreter. False elsewhere."""
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError, ValueError):
        return False


def die_with_parent(parent: int | None = None, sentinel=None, interval: float = 0.5) -> bool:
    """End this worker process within moments of its parent's death (the master of a local run, the
    launcher's proxy under mpiexec or srun), whatever it is doing: its task stays pending in the store
    (only the master writes it) and the next run computes it.

    On Linux the kernel kills it (``PR_SET_PDEATHSIG``, SIGKILL); besides, a watcher thread waits on
    ``sentinel`` (a connection or file descriptor that ends with the parent, e.g. multiprocessing's
    parent sentinel) or polls ``os.getppid()`` (a dead parent's children are handed to another
    process), and ends the process (``os._exit``): for other systems, and for a parent that died
    before the request. Returns whether the kernel will do it."""
    import threading

    parent = os.getppid() if parent is None else int(parent)
    kernel = _parent_death_signal()
    if os.getppid() != parent:  # it died before we asked
        os._exit(0)

    def watch():
        if sentinel is not None:
            try:
                from multiprocessing.connection import wait

                wait([sentinel])
            except (OSError, ValueError):
                pass
            else:
                os._exit(0)
        while os.getppid() == parent:
            time.sleep(interval)
        os._exit(0)

    threading.Thread(target=watch, name="campaign-parent-watch", daemon=True).start()
    return kernel


def master_gone(pid: int | None, host: str | None) -> bool:
    """Whether the master process ``pid`` on ``host`` is known to be gone (only on its own host;
    elsewhere the launcher ends the job's ranks when one dies)."""
    if not pid or host != _HOST:
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    try:  # a killed process its parent has not reaped yet (a zombie) is gone too
        with open(f"/proc/{int(pid)}/stat", "rb") as fh:
            return fh.read().rsplit(b")", 1)[-1].split()[0] in (b"Z", b"X")
    except (OSError, IndexError):
        return False


# --------------------------------------------------------------------------- worker loop

def worker_loop(recv, send, context: dict, rank: int, poll=None) -> None:
    """Serve tasks until told to stop.

    ``recv()`` returns ``("task", payload)`` or ``("stop",)``; ``send(msg)``
    sends ``("ready", rank)`` once the task function is loaded (and its kernels
    warmed up), then ``("result", index, attempt, summary)`` per task. Signals meant for the whole
    job (Ctrl-C, SIGTERM from a scheduler, SLURM's USR1 warning) are the master's business:
    a worker ignores them and finishes its task; the master decides when to stop.

    Batches: with ``poll()`` (True when a message is waiting) and ``context["gpu_batch"]`` > 1, a
    ``device: gpu`` task is run together with the tasks already waiting behind it that share its
    ``batch_key``, up to ``gpu_batch`` of them, in one launch; a task of another key waits for the
    next round. A GPU worker whose task function has ``start_batch``, ``finish_batch`` and
    ``analyse`` hands its messages to an event loop instead (``campaign.run.gpuworker.GpuLoop``):
    several launches in flight, each gathered before it starts, their packings analysed while the
    GPU runs the others, and, with a deadline, launches that stop at a step budget and hand their
    suspended packings back (``("suspended", index, attempt, record)``).
    """
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1):
        try:
            signal.signal(sig, signal.SIG_IGN)
        except (ValueError, OSError):
            pass
    if context.get("gpu_device") is not None:  # this worker's GPU, before anything starts CUDA
        os.environ["CUDA_VISIBLE_DEVICES"] = visible_device(context["gpu_device"])
    try:
        fn = resolve(context.get("task_function"))
    except Exception:  # noqa: BLE001 - report on the first task instead of dying silently
        err = traceback.format_exc()
        fn = None
    if fn is not None and hasattr(fn, "warm_up") and context.get("warm_up", True):
        try:  # load the compiled kernels now, so that no task's timing includes it
            fn.warm_up(context)
        except Exception:  # noqa: BLE001 - a real problem shows up again in the first task
            pass
    send(("ready", rank))
    limit = int(context.get("gpu_batch") or 1) if context.get("gpu_device") is not None else 1
    if (context.get("gpu_device") is not None and poll is not None
            and all(hasattr(fn, m) for m in ("start_batch", "finish_batch", "analyse"))):
        from campaign.run.gpuworker import GpuLoop

        GpuLoop(fn, context, rank, recv, send, poll, _summary,
                lambda payload: run_task(fn, payload, context, rank), batch_key, limit=limit).serve()
        return
    held = None  # a message read while filling a batch that belongs to the next round
    while True:
        msg, held = (held, None) if held is not None else (recv(), None)
        if msg is None or msg[0] == "stop":
            return
        payload = msg[1]
        if fn is None:
            summary = {"id": payload["id"], "ok": False, "scalars": {}, "histograms": {},
                       "configuration": None, "wall": 0.0, "rank": rank, "host": _HOST,
                       "error": {"message": "cannot load the task function", "traceback": err}}
            send(("result", payload["index"], payload.get("attempt", 1), summary))
            continue
        key = batch_key(payload)
        batch = [payload]
        if key is not None and limit > 1 and poll is not None and hasattr(fn, "run_batch"):
            while len(batch) < limit and poll():
                nxt = recv()
                if nxt is not None and nxt[0] == "task" and batch_key(nxt[1]) == key:
                    batch.append(nxt[1])
                else:
                    held = nxt if nxt is not None else ("stop",)
                    break
        summaries = (run_tasks(fn, batch, context, rank) if len(batch) > 1
                     else [run_task(fn, payload, context, rank)])
        for p, summary in zip(batch, summaries):
            send(("result", p["index"], p.get("attempt", 1), summary))
