"""Do the Newton endgame and FIRE alone make the same packings?

    python experiments/newton_equivalence.py results/newton.h5 [--variant newton] [--reference default]

Reads a store of campaigns/newton.yaml (configurations kept), pairs each packing of the
Newton variant with the reference's packing of the same (N, E, seed) (both from the same
random start) and prints, per N and over all: the pairs; the fraction whose final energy is
the same to 1e-9 relative (the O'Hern searches took the same radius steps); among those, the
fraction whose load-bearing contact network (the non-rattler contacts, kernels.network) is
identical, and the largest displacement of a load-bearing disk (translations removed) in
units of the typical overlap; over all pairs, the mean relative difference of E_G, the
mean difference of N_G / N (rattler count) and the mean difference of Delta Z over the pairs
of the same energy and over the others, with standard errors.
"""

import argparse
import sys

import h5py
import numpy as np

from kernels.network import network


def _config(f, tid):
    g = f[f"configurations/{tid}"]
    return g["positions"][()], g["radii"][()], g["box"][()]


def _bonds(pos, rad, box):
    net = network(pos, rad, box)
    return set(zip(net["bi"].tolist(), net["bj"].tolist())), ~net["rattler"]


def _mean(x):
    if len(x) < 2:
        return "-"
    return f"{x.mean():+.1e} +- {x.std(ddof=1) / np.sqrt(len(x)):.1e} ({len(x)})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--variant", default="newton")
    ap.add_argument("--reference", default="default")
    args = ap.parse_args(argv)
    with h5py.File(args.store, "r") as f:
        t = f["tasks"]
        ok = t["status"][()] == 1
        ids = [s.decode() for s in t["id"][()]]
        var = [s.decode() for s in t["variant"][()]]
        key = list(zip(t["N"][()], t["E"][()], t["seed"][()]))
        eg = f["scalars/E_G"][()]
        ng = f["scalars/N_G"][()]
        dz = f["scalars/delta_Z"][()]
        where = {(var[k], key[k]): k for k in range(len(ids)) if ok[k]}
        rows = {}
        for (v, kk), k in where.items():
            if v != args.variant or (args.reference, kk) not in where:
                continue
            r = where[(args.reference, kk)]
            n = kk[0]
            d_e = (eg[k] - eg[r]) / eg[r]
            d_ng = (ng[k] - ng[r]) / n
            same_e = abs(d_e) <= 1e-9
            same_net, disp = False, np.nan
            if same_e:
                pk, rad, box = _config(f, ids[k])
                pr, _, _ = _config(f, ids[r])
                bk, alive_k = _bonds(pk, rad, box)
                br, alive_r = _bonds(pr, rad, box)
                same_net = bk == br and np.array_equal(alive_k, alive_r)
                if same_net:
                    d = pk - pr
                    d -= box * np.round(d / box)
                    d -= d[alive_r].mean(axis=0)
                    x_typ = np.sqrt(eg[r]) * 2 * rad.mean()  # harmonic: overlap ~ sqrt(E_G)
                    disp = float(np.abs(d[alive_r]).max() / x_typ)
            rows.setdefault(n, []).append((d_e, d_ng, same_e, same_net, disp, dz[k] - dz[r]))
    if not rows:
        print(f"no pairs of variants {args.variant!r} and {args.reference!r} in {args.store}", file=sys.stderr)
        return 2
    print("| N | pairs | same energy | same network (of same energy) | largest displacement / typical "
          "overlap (median, max) | mean dE_G / E_G | mean d(N_G / N) | mean dDelta_Z, same energy | "
          "mean dDelta_Z, other pairs |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in sorted(rows) + ["all"]:
        rr = [x for m in sorted(rows) for x in rows[m]] if n == "all" else rows[n]
        d_e = np.array([x[0] for x in rr])
        d_ng = np.array([x[1] for x in rr])
        se = np.array([x[2] for x in rr])
        sn = np.array([x[3] for x in rr])
        disp = np.array([x[4] for x in rr if x[3]])
        dd = f"{np.median(disp):.1e}, {disp.max():.1e}" if len(disp) else "-"
        dzs = [_mean(np.array([x[5] for x in rr if x[2] == same])) for same in (True, False)]
        print(f"| {n} | {len(rr)} | {se.mean():.3f} | {sn.sum() / max(se.sum(), 1):.3f} | {dd} | "
              f"{d_e.mean():+.1e} +- {d_e.std(ddof=1) / np.sqrt(len(rr)):.1e} | "
              f"{d_ng.mean():+.2e} +- {d_ng.std(ddof=1) / np.sqrt(len(rr)):.1e} | {dzs[0]} | {dzs[1]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
