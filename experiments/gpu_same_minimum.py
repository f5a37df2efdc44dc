"""How often the GPU block (its CPU emulation) ends in the minimum the CPU search ends in from the same
seed: positions equal up to a translation (1e-3 radii) and A_G per packing (docs/GPU.md).

    python experiments/gpu_same_minimum.py [--seeds 8]
"""

import argparse

import numpy as np

import kernels
from kernels.gpu import jam_batch


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    a = ap.parse_args(argv)
    seeds = list(range(a.seeds))
    for n, e in ((64, 1e-6), (256, 1e-10), (1024, 1e-6)):
        gpu = jam_batch(n, [e] * len(seeds), seeds, backend="emulate")
        same, d_a = 0, []
        for s, p in zip(seeds, gpu):
            c = kernels.jam(n, e, s)
            d = ((p.positions - c.positions) + 0.5) % 1.0 - 0.5
            d = ((d - np.median(d, axis=0)) + 0.5) % 1.0 - 0.5  # the translation the two runs drifted apart by
            same += bool(np.abs(d).max() < 1e-3 * c.radii.mean())
            d_a.append(kernels.analyze(p.positions, p.radii, p.box).scalars["A_G"]
                       - kernels.analyze(c.positions, c.radii, c.box).scalars["A_G"])
        print(f"N_G {n:5d} E_G {e:g}: {same}/{len(seeds)} in the CPU packing's minimum up to a translation; "
              f"A_G(GPU) - A_G(CPU): {' '.join(f'{x:+.5f}' for x in d_a)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
