"""Benchmark of the packing kernels: per-step cost and time to a jammed packing.

For each N (default 256, 1024, 4096):

* per-step cost of our FIRE 2.0 loop: a fixed number of steps relaxing a packing
  jammed at E_G = 1e-4 after a small shrink (Verlet list with the default skin,
  harmonic potential, float64), median over seeds of wall time / steps;
* the same measurement with JAX MD's ``minimize.fire_descent`` on the CPU (float64,
  ``energy.soft_sphere_neighbor_list`` with the same exponent, contact distances
  ``sigma_ij = r_i + r_j`` and skin, 25 steps with neighbour-list updates unrolled
  in one jitted function, timed after a warm-up call), when ``jax`` and ``jax_md`` are importable (the optional
  ``bench`` extra: ``pip install '.[bench]'``);
* time to a jammed packing, ``kernels.jam(N, E, seed)``, for each E (default 1e-6
  and 1e-16), median over seeds, with force evaluations and O'Hern iterations. The
  force tolerance is the default 1e-6, or the first decade above the float64 floor
  (``kernels.jamming.energy_floor``) where 1e-6 is refused (N = 4096 at 1e-16).
  With ``--minimizers fire cg`` every packing is made with each minimiser in turn
  (same N, E, seed, one after the other, so that both see the same machine load) and
  a second table gives the ratios of the medians, CG / FIRE. ``paper`` is the paper's
  literal protocol: CG stopped by the energy-change rule, Delta halved after every
  minimisation (``MINIMIZERS``). ``newton`` is FIRE with the sparse Newton endgame
  (``endgame="newton"``, ``kernels.newton``): its rows add the factorisations and where
  the time goes (the force evaluations at the per-evaluation cost FIRE paid on the same
  seed, the rest being Hessian assembly, ordering, factorisation and solves). ``shear``
  relaxes the cell's tilt and aspect ratio with the disks (``cell="shear"``,
  ``kernels.cellrelax``).

With ``--routes ohern pressure`` the time to jam is measured for each route of
``kernels.jam`` (``route=...``, see ``kernels.barostat``) side by side, seed by seed, and
the table gives the ratio of the median force evaluations (and times) to the first
route. ``--profile`` adds, for each route, the force evaluations spent in each
minimisation (the k-th from the difference of two runs bounded by ``max_search = k``
and ``k - 1``: the searches are deterministic), median over seeds.

Prints a table and, with ``--json FILE``, writes every measurement as JSON. For the
one-core comparison run it pinned to one CPU, e.g. ``taskset -c 0`` (XLA then uses
one thread, numba kernels are serial anyway).

    python benchmarks/bench_jam.py --json bench.json
    python benchmarks/bench_jam.py --sizes 256 1024 --energies 1e-6 --seeds 2   # quick
    python benchmarks/bench_jam.py --no-steps --sizes 256 1024 --energies 1e-6 1e-12 1e-16 \
        --seeds 5 --minimizers fire cg paper                                    # docs/MINIMIZERS.md
    python benchmarks/bench_jam.py --no-steps --sizes 256 1024 4096 --energies 1e-6 1e-12 1e-16 \
        --seeds 5 --minimizers fire newton --json newton.json                   # docs/NEWTON.md
    python benchmarks/bench_jam.py --no-steps --no-jax --sizes 1024 --energies 1e-12 --seeds 8 \
        --minimizers fire shear                                                 # docs/SHEAR.md
    python benchmarks/bench_jam.py --no-jax --sizes 1024 --energies 1e-16 --steps 10 \
        --routes ohern pressure --seeds 20 --json routes.json                   # docs/PRESSURE_ROUTE.md
"""

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np


def _our_step_cost(n, seed, steps, exponent=2.0):
    """Per-step cost of our FIRE loop on a relaxing near-jammed state.

    The state is a packing jammed at E_G = 1e-4 whose radii are then shrunk by a
    quarter of the typical overlap, so that every step does real work, as in the
    O'Hern search. Tolerance 0: exactly ``steps`` steps are taken.
    """
    import kernels
    from kernels.fire import _fire_core
    from kernels.jamming import DEFAULTS
    from kernels.protocol import _dt_for, _spatial_order
    from kernels.space import _as_box

    p = kernels.jam(n, 1e-4, seed)
    box = _as_box(p.box)  # the kernels' cell [Lx, Ly, xy]
    # the order jam() works in (disks sorted by cell), used for both codes
    perm = _spatial_order(np.array(p.positions), box, 2.0 * float(np.mean(p.radii)))
    rad = np.array(p.radii)[perm] * (1.0 - 0.25 * np.sqrt(2e-4))
    pos = np.array(p.positions)[perm]
    skin = DEFAULTS["skin"] * 2.0 * rad.mean()
    dt0 = _dt_for(rad, exponent, 1e-4)
    _fire_core(pos.copy(), rad, box, exponent, 0.0, 5, skin, dt0, 0.0)  # warm
    q = pos.copy()
    t = time.perf_counter()
    out = _fire_core(q, rad, box, exponent, 0.0, steps, skin, dt0, 0.0)
    wall = time.perf_counter() - t
    return wall / out[2], pos, rad, box, skin


def _jaxmd_step_cost(pos, rad, box, skin, steps, exponent=2.0):
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_platforms", "cpu")
    import jax.numpy as jnp
    from jax_md import energy, minimize, space

    n = len(rad)
    radii = np.unique(rad)
    species = np.searchsorted(radii, rad)
    sigma = radii[:, None] + radii[None, :]
    disp, shift = space.periodic(jnp.asarray(box))
    neighbor_fn, energy_fn = energy.soft_sphere_neighbor_list(
        disp, jnp.asarray(box), species=jnp.asarray(species), sigma=jnp.asarray(sigma),
        epsilon=1.0, alpha=exponent, dr_threshold=skin, fractional_coordinates=False)
    R = jnp.asarray(pos)
    nbrs = neighbor_fn.allocate(R)
    s = 2.0 * rad.mean()
    init, apply = minimize.fire_descent(energy_fn, shift, dt_start=0.04 * s, dt_max=0.4 * s)

    # cross-check: same potential as ours
    from kernels.potential import energy as our_energy

    e_jax = float(energy_fn(R, neighbor=nbrs))
    e_ours = our_energy(pos, rad, box, exponent)
    if not np.isclose(e_jax, e_ours, rtol=1e-9):
        raise RuntimeError(f"JAX MD energy {e_jax} differs from ours {e_ours}")

    # CHUNK steps unrolled in one compiled function (the neighbour list's pytree
    # metadata cannot be carried through lax.fori_loop), called steps // CHUNK times
    chunk = 25

    @jax.jit
    def run_chunk(state, nbrs):
        for _ in range(chunk):
            state = apply(state, neighbor=nbrs)
            nbrs = nbrs.update(state.position)
        return state, nbrs

    def run(state, nbrs, k):
        for _ in range(max(1, k // chunk)):
            state, nbrs = run_chunk(state, nbrs)
        return state, nbrs

    state = init(R, neighbor=nbrs)
    out = run(state, nbrs, chunk)  # compile
    jax.block_until_ready(out[0].position)
    if bool(out[1].did_buffer_overflow):
        nbrs = neighbor_fn.allocate(out[0].position, extra_capacity=64)
        state = init(R, neighbor=nbrs)
        out = run(state, nbrs, chunk)
        jax.block_until_ready(out[0].position)
    steps = max(chunk, steps // chunk * chunk)
    t = time.perf_counter()
    out = run(state, nbrs, steps)
    jax.block_until_ready(out[0].position)
    wall = time.perf_counter() - t
    overflow = bool(out[1].did_buffer_overflow)
    return wall / steps, overflow


def _jaxmd_in_subprocess(n, seed, steps):
    """JAX MD per-step cost in a fresh interpreter: a second neighbour list with
    other cell parameters in the same process trips over pytree metadata that holds
    arrays (jax 0.10.2, jax-md 0.2.29)."""
    import subprocess

    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--_jaxmd", str(n),
                          str(seed), str(steps)], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(out.stderr.strip().splitlines()[-1] if out.stderr else "failed")
    cost, overflow = json.loads(out.stdout.strip().splitlines()[-1])
    return cost, overflow


def _jaxmd_child(n, seed, steps):
    _, pos, rad, box, skin = _our_step_cost(n, seed, 10)
    cost, overflow = _jaxmd_step_cost(pos, rad, box, skin, steps)
    print(json.dumps([cost, overflow]))
    return 0


#: jam() settings of each minimiser label of ``--minimizers``
MINIMIZERS = {
    "fire": {},
    "cg": {"minimizer": "cg"},
    "paper": {"minimizer": "cg", "stop": "energy", "search": "paper"},
    "newton": {"endgame": "newton"},
    "shear": {"cell": "shear"},
}


def _jam_time(n, e, seed, **settings):
    import kernels

    t = time.perf_counter()
    p = kernels.jam(n, e, seed, **settings)
    wall = time.perf_counter() - t
    return dict(seconds=wall, status=p.status, energy=p.energy, phi=p.phi,
                force_residual=p.force_residual, iterations=p.iterations,
                force_evaluations=p.force_evaluations, n_nonrattlers=p.n_nonrattlers,
                factorizations=p.factorizations)


def _profile(n, e, seed, **settings):
    """Force evaluations of each minimisation of one search (see module docstring)."""
    import kernels

    total = kernels.jam(n, e, seed, **settings)
    per, prev = [], 0
    for k in range(1, total.iterations + 1):
        cum = (total.force_evaluations if k == total.iterations
               else kernels.jam(n, e, seed, max_search=k, **settings).force_evaluations)
        per.append(cum - prev)
        prev = cum
    return per


def _tolerance_for(n, e):
    """The default force tolerance, or the first decade above the float64 floor."""
    from kernels.jamming import DEFAULTS, energy_floor, initial_state

    _, rad, _ = initial_state(n, 0, DEFAULTS["box"], DEFAULTS["species"], DEFAULTS["phi_start"])
    tol = DEFAULTS["force_tolerance"]
    while energy_floor(rad, np.asarray(DEFAULTS["box"], float), DEFAULTS["exponent"], tol) > e:
        tol *= 10.0
    return tol


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--_jaxmd":
        return _jaxmd_child(int(argv[1]), int(argv[2]), int(argv[3]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024, 4096])
    ap.add_argument("--energies", type=float, nargs="+", default=[1e-6, 1e-16])
    ap.add_argument("--seeds", type=int, default=5, help="seeds per point (median)")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="time to jam: seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--steps", type=int, default=2000, help="FIRE steps per step-cost sample")
    ap.add_argument("--no-jax", action="store_true", help="skip the JAX MD comparison")
    ap.add_argument("--no-jam", action="store_true", help="skip the time-to-jam part")
    ap.add_argument("--no-steps", action="store_true", help="skip the per-step cost part")
    ap.add_argument("--minimizers", nargs="+", default=["fire"], choices=sorted(MINIMIZERS),
                    help="jam with each of these (fire, cg, paper, newton); ratios to the first")
    ap.add_argument("--routes", nargs="+", default=["ohern"], choices=["ohern", "pressure"],
                    help="routes of kernels.jam to time side by side (ratios to the first)")
    ap.add_argument("--profile", action="store_true",
                    help="force evaluations per minimisation of each variant (median over seeds)")
    ap.add_argument("--json", metavar="FILE", help="write all measurements as JSON")
    args = ap.parse_args(argv)

    import numba

    import kernels

    for m in args.minimizers:  # load or compile the numba cache outside the timings
        kernels.jam(64, 1e-4, 0, **MINIMIZERS[m])
    have_jax = False
    if not args.no_jax:
        try:
            import jax  # noqa: F401
            import jax_md  # noqa: F401
            have_jax = True
        except ImportError as exc:  # the optional `bench` extra is not installed
            print(f"# JAX MD not available ({exc}); install '.[bench]' to compare",
                  file=sys.stderr)

    results = dict(
        machine=dict(python=platform.python_version(), numpy=np.__version__,
                     numba=numba.__version__, cpu=platform.processor() or platform.machine(),
                     threads_numba=numba.get_num_threads(), cpus=os.cpu_count()),
        step_cost=[], time_to_jam=[])
    if have_jax:
        import jax
        import importlib.metadata as md

        results["machine"]["jax"] = jax.__version__
        results["machine"]["jax_md"] = md.version("jax-md")

    for n in ([] if args.no_steps else args.sizes):
        ours, theirs, overflow = [], [], False
        for seed in range(args.seeds):
            c, pos, rad, box, skin = _our_step_cost(n, seed, args.steps)
            ours.append(c)
            if have_jax and seed < max(1, min(args.seeds, 3)):
                j, ov = _jaxmd_in_subprocess(n, seed, args.steps)
                theirs.append(j)
                overflow |= ov
        row = dict(n=n, ours_us=1e6 * statistics.median(ours),
                   jaxmd_us=1e6 * statistics.median(theirs) if theirs else None,
                   jaxmd_neighbor_overflow=overflow if theirs else None)
        row["speedup"] = row["jaxmd_us"] / row["ours_us"] if theirs else None
        results["step_cost"].append(row)
        print(f"step cost N={n}: ours {row['ours_us']:.1f} us"
              + (f", JAX MD {row['jaxmd_us']:.1f} us, ratio {row['speedup']:.1f}x"
                 if theirs else ""), flush=True)

    if not args.no_jam:
        for e in args.energies:
            for n in args.sizes:
                tol = _tolerance_for(n, e)
                # every (minimiser, route) pair, interleaved seed by seed: the same machine load
                variants = [(m if len(args.routes) == 1 else f"{m}/{route}" if len(args.minimizers) > 1
                             else route, dict(MINIMIZERS[m], route=route))
                            for m in args.minimizers for route in args.routes]
                runs = {label: [] for label, _ in variants}
                seeds = range(args.first_seed, args.first_seed + args.seeds)
                for seed in seeds:
                    for label, kw in variants:
                        runs[label].append(_jam_time(n, e, seed, force_tolerance=tol, **kw))
                base = None
                for label, kw in variants:
                    rr = runs[label]
                    row = dict(n=n, energy=e, force_tolerance=tol, variant=label, settings=kw,
                               median_seconds=statistics.median(r["seconds"] for r in rr),
                               median_force_evaluations=statistics.median(
                                   r["force_evaluations"] for r in rr),
                               median_iterations=statistics.median(r["iterations"] for r in rr),
                               median_residual=statistics.median(r["force_residual"] for r in rr),
                               converged=sum(r["status"] == "converged" for r in rr),
                               runs=rr)
                    if base is None:
                        base = row
                    row["force_evaluation_ratio"] = (row["median_force_evaluations"]
                                                     / base["median_force_evaluations"])
                    row["time_ratio"] = row["median_seconds"] / base["median_seconds"]
                    row["median_factorizations"] = statistics.median(r["factorizations"] for r in rr)
                    if kw.get("endgame") == "newton" and base is not row:
                        # where the time goes: the force evaluations at the cost per evaluation
                        # the first variant paid on the same seed, and everything else (Hessian
                        # assembly, ordering, factorisation, solves)
                        forces = [r["force_evaluations"] * b["seconds"] / b["force_evaluations"]
                                  for r, b in zip(rr, base["runs"])]
                        row["median_force_seconds"] = statistics.median(forces)
                        row["median_linear_algebra_seconds"] = statistics.median(
                            r["seconds"] - f for r, f in zip(rr, forces))
                        row["median_seed_time_ratio"] = statistics.median(
                            r["seconds"] / b["seconds"] for r, b in zip(rr, base["runs"]))
                    if args.profile:
                        prof = [_profile(n, e, seed, force_tolerance=tol, **kw) for seed in seeds]
                        row["profile"] = prof
                        depth = max(len(p) for p in prof)
                        row["median_profile"] = [statistics.median(p[k] for p in prof if len(p) > k)
                                                 for k in range(depth)]
                        print(f"profile N={n} E={e:g} {label}: force evaluations per "
                              f"minimisation (median) {[int(x) for x in row['median_profile']]}",
                              flush=True)
                    results["time_to_jam"].append(row)
                    print(f"jam N={n} E={e:g} tol={tol:g} {label}: median {row['median_seconds']:.2f} s, "
                          f"{row['median_force_evaluations']:.0f} force evaluations, "
                          f"{row['converged']}/{len(rr)} converged"
                          + (f", {row['median_factorizations']:.0f} factorisations"
                             if row["median_factorizations"] else ""), flush=True)

    if results["step_cost"]:
        print()
        print("| N | ours per step (us) | JAX MD per step (us) | ratio |")
        print("|---:|---:|---:|---:|")
    for r in results["step_cost"]:
        j = f"{r['jaxmd_us']:.1f}" if r["jaxmd_us"] else "n/a"
        s = f"{r['speedup']:.1f}x" if r["speedup"] else "n/a"
        print(f"| {r['n']} | {r['ours_us']:.1f} | {j} | {s} |")
    if results["time_to_jam"]:
        print()
        print("| N | E | force tolerance | variant | median time to jam (s) | "
              "median force evaluations | ratio to the first (evaluations / time) | "
              "median iterations | median force residual | converged |")
        print("|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|")
        for r in results["time_to_jam"]:
            print(f"| {r['n']} | {r['energy']:g} | {r['force_tolerance']:g} | {r['variant']} | "
                  f"{r['median_seconds']:.2f} | {r['median_force_evaluations']:.0f} | "
                  f"{r['force_evaluation_ratio']:.2f} / {r['time_ratio']:.2f} | "
                  f"{r['median_iterations']:.0f} | {r['median_residual']:.2g} | "
                  f"{r['converged']}/{len(r['runs'])} |")
    split = [r for r in results["time_to_jam"] if "median_force_seconds" in r]
    if split:
        print()
        print("| N | E | variant | median time (s) | median of the per-seed time ratios | "
              "median factorisations | force evaluations (s, est.) | linear algebra (s, est.) |")
        print("|---:|---:|---|---:|---:|---:|---:|---:|")
        for r in split:
            print(f"| {r['n']} | {r['energy']:g} | {r['variant']} | {r['median_seconds']:.2f} | "
                  f"{r['median_seed_time_ratio']:.2f} | {r['median_factorizations']:.0f} | "
                  f"{r['median_force_seconds']:.2f} | {r['median_linear_algebra_seconds']:.2f} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
