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
* ``"package.module:attribute"``: any object with ``run(payload, context)``
  and ``histogram_edges(context)`` (and optionally ``warm_up(context)``).

Workers never raise: ``run_task`` returns the contract's summary dict with
``ok=False`` and an error record (message, traceback) when anything fails.
"""

from __future__ import annotations

import importlib
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
        per protocol of ``context["protocol_warmups"]`` (the engine's list of distinct choices)."""
        for protocol in context.get("protocol_warmups") or [{}]:
            self.run({"N": 16, "E": 1e-3, "entropy": [0], "protocol": protocol}, context)

    def run(self, payload, context):
        import kernels

        # the variant's system (a spec's variants may override it), else the spec's
        system = (context.get("systems") or {}).get(payload.get("variant"), context["system"])
        exponent = system["potential"]["exponent"]
        protocol = dict(payload["protocol"])
        if "sizes" in system:
            protocol["sizes"] = (system["sizes"]["distribution"], system["sizes"]["polydispersity"])
        else:
            protocol["species"] = tuple((f, r) for _, f, r in system["species"])
        protocol.pop("start", None)  # "ladder": the master sends the parent's packing as payload["start"]
        start = payload.get("start")
        if start is not None:
            start = (start["positions"], start["radii"], start["species"], start["box"])
        t0 = time.perf_counter()
        p = kernels.jam(payload["N"], payload["E"], list(payload["entropy"]), start=start,
                        box=tuple(system["box"]), exponent=exponent, **protocol)
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
                       sigma_max=float(np.max(p.radii)), jam_seconds=t1 - t0, analyze_seconds=t2 - t1)
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
        return scalars, hists, config


def _matches(spec: str, payload) -> bool:
    for item in filter(None, (s.strip() for s in spec.split(","))):
        if item.startswith("seed:") and payload["seed"] == int(item[5:]):
            return True
        if item.startswith("N:") and payload["N"] == int(item[2:]):
            return True
        if ":" not in item and payload["id"].startswith(item):
            return True
    return False


#: Bins per histogram of kernels.analysis.DEFAULT_BINS (tests/test_store.py checks they agree);
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
        config = None
        if context.get("configurations") or payload.get("return_configuration"):
            pos = rng.random((N, 2))
            config = {"positions": pos, "radii": np.where(np.arange(N) < N // 2, 1.4, 1.0) * 0.01,
                      "box": np.array([1.0, 1.0]), "species": (np.arange(N) >= N // 2).astype(np.int32)}
        return scalars, hists, config


def resolve(name: str):
    """The task function object for a name from the run context."""
    if name in ("kernels", None, ""):
        return KernelTask()
    if name == "synthetic":
        return SyntheticTask()
    module, _, attr = name.partition(":")
    obj = getattr(importlib.import_module(module), attr)
    return obj() if isinstance(obj, type) else obj


# --------------------------------------------------------------------------- one task

def run_task(fn, payload: dict, context: dict, rank: int = 0) -> dict:
    """Run one task; never raises. Returns the summary dict of docs/CONTRACTS.md."""
    t0 = time.perf_counter()
    summary = {"id": payload["id"], "ok": False, "scalars": {}, "histograms": {}, "configuration": None,
               "wall": 0.0, "rank": rank, "host": _HOST, "error": None}
    try:
        scalars, hists, config = fn.run(payload, context)
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
                              "traceback": traceback.format_exc()[-20000:]})
    summary["wall"] = time.perf_counter() - t0
    return summary


# --------------------------------------------------------------------------- worker loop

def worker_loop(recv, send, context: dict, rank: int) -> None:
    """Serve tasks until told to stop.

    ``recv()`` returns ``("task", payload)`` or ``("stop",)``; ``send(msg)``
    sends ``("ready", rank)`` once the task function is loaded (and its kernels
    warmed up), then ``("result", index, attempt, summary)`` per task. Signals meant for the whole
    job (Ctrl-C, SIGTERM from a scheduler, SLURM's USR1 warning) are the master's business:
    a worker ignores them and finishes its task; the master decides when to stop.
    """
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1):
        try:
            signal.signal(sig, signal.SIG_IGN)
        except (ValueError, OSError):
            pass
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
    while True:
        msg = recv()
        if msg is None or msg[0] == "stop":
            return
        payload = msg[1]
        if fn is None:
            summary = {"id": payload["id"], "ok": False, "scalars": {}, "histograms": {},
                       "configuration": None, "wall": 0.0, "rank": rank, "host": _HOST,
                       "error": {"message": "cannot load the task function", "traceback": err}}
        else:
            summary = run_task(fn, payload, context, rank)
        send(("result", payload["index"], payload.get("attempt", 1), summary))

