"""What the half-plane rattler rule changes: the same spec run before and after it.

    python experiments/rattler_rule.py BEFORE.h5 AFTER.h5

Pairs the finished packings of the two stores by task id (ids do not depend on the
code version) and prints, per variant: packings compared, packings whose jam changed
(a different E_G: the minimiser's residual counts other disks now, so it may stop at
another step), packings whose rattler count changed, the mean rattlers per packing
before and after, the grains that became rattlers, and the packings the reducer must
leave out (``identities_ok != 1``) before and after.
"""

import sys

import h5py
import numpy as np


def load(path):
    with h5py.File(path, "r") as f:
        t = f["tasks"]
        ok = t["status"][:] == 1
        ids = t["id"][:][ok]
        var = t["variant"][:][ok]
        s = {k: f["scalars"][k][:][ok] for k in ("N", "N_R", "E_G", "identities_ok", "jam_status")}
    return {i: (v, {k: s[k][n] for k in s}) for n, (i, v) in enumerate(zip(ids, var))}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    before, after = load(argv[0]), load(argv[1])
    common = sorted(set(before) & set(after))
    print("| variant | packings | jam changed | rattler count changed | rattlers per packing before | after | "
          "grains turned rattler (all packings) | left out before | after |")
    print("|---|---|---|---|---|---|---|---|---|")
    for v in sorted({before[i][0] for i in common}):
        ids = [i for i in common if before[i][0] == v]
        b = {k: np.array([before[i][1][k] for i in ids]) for k in before[ids[0]][1]}
        a = {k: np.array([after[i][1][k] for i in ids]) for k in after[ids[0]][1]}
        changed = int(np.count_nonzero(a["E_G"] != b["E_G"]))
        nr = int(np.count_nonzero(a["N_R"] != b["N_R"]))
        out_b = int(np.count_nonzero((b["identities_ok"] != 1) | (b["jam_status"] != 0)))
        out_a = int(np.count_nonzero((a["identities_ok"] != 1) | (a["jam_status"] != 0)))
        print(f"| {v.decode() if isinstance(v, bytes) else v} | {len(ids)} | {changed} | {nr} | {b['N_R'].mean():.2f} | "
              f"{a['N_R'].mean():.2f} | {int((a['N_R'] - b['N_R']).sum())} | {out_b} | {out_a} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
