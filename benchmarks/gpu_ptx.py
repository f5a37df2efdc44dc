"""What the GPU block costs in registers, spills and instructions, without a GPU.

Compiles the batch kernel (``kernels.gpu.device.kernel``) for Hopper (sm_90) as a launch does
(no contraction, no link-time optimisation), assembles it with ``ptxas -v`` at the register
bounds that let one or two blocks of each size fit an SM, and prints per block size and bound:
registers per thread, spill stores and loads and stack (bytes per thread), shared memory per
block, the blocks and warps an SM holds (sm_90: 65536 registers, 2048 threads, 32 blocks, 228
KiB of shared memory; registers allocated per warp in units of 256), and the instructions of
the innermost loop of the forces phase (one pair of a neighbour row) in the PTX.

    python benchmarks/gpu_ptx.py [--threads 256 512 1024] [--exponent 2.0] [--json FILE]

Needs numba-cuda with its CUDA compiler libraries and ``ptxas`` (``pip install '.[cuda]'``, whose
``nvidia-cuda-nvcc`` wheel brings it; ``PTXAS`` names another, else the first on the ``PATH``).
A PTX newer than an older assembler is relabelled with the assembler's version (the kernel uses
nothing newer: the assembler refuses what it does not know).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SM90 = {"registers": 65536, "threads": 2048, "blocks": 32, "shared": 228 * 1024, "unit": 256}


def find_ptxas() -> str | None:
    """``PTXAS``, the ``nvidia-cuda-nvcc`` wheel's (the ``cuda`` extra), or the ``PATH``'s."""
    if os.environ.get("PTXAS"):
        return os.environ["PTXAS"]
    for base in sys.path:
        for cu in ("cu13", "cu12"):
            cand = Path(base or ".") / "nvidia" / cu / "bin" / "ptxas"
            if cand.is_file() and os.access(cand, os.X_OK):
                return str(cand)
    return shutil.which("ptxas")


def _hopper():
    """Compile for compute capability 9.0 without a device."""
    import numba.cuda.dispatcher as d

    class Hopper:
        compute_capability = (9, 0)

    d.get_current_device = lambda: Hopper()


def kernel_ptx(nt: int, exponent) -> str:
    """The batch kernel's PTX for blocks of ``nt`` threads, compiled as a launch does."""
    _hopper()
    from numba import cuda, float64, int32

    from kernels.gpu import device

    f3, f2, i3, i1 = float64[:, :, ::1], float64[:, ::1], int32[:, :, ::1], int32[::1]
    k = device.kernel(nt, exponent)
    with device._uncontracted():
        ptx, _ = cuda.compile_ptx(k.py_func, (i1, f3, f3, i3, f3, i3, i3, f2, f2), device=False,
                                  cc=(9, 0))
    return ptx


def forces_ptx(exponent) -> str:
    """The PTX of a kernel that runs the forces phase alone (its pair loop is found there)."""
    _hopper()
    from numba import cuda, float64, int32

    from kernels.gpu import device
    from kernels.gpu.block import make_block
    from kernels.gpu.state import N_ST, ROWS, WARP

    dev = cuda.jit(device=True)
    forces = make_block(dev, dev(device._sync), dev(device._slot_add), dev(device._put_sum),
                        dev(device._put_max), dev(device._total), dev(device._now), exponent).forces

    def run(xy, fl, nbr, ninv, iv):
        t = cuda.threadIdx.x
        red = cuda.shared.array((ROWS, WARP), dtype=float64)
        sh = cuda.shared.array(N_ST, dtype=float64)
        forces(t, t + 1, cuda.blockDim.x, xy, fl, nbr, ninv, iv, red, sh)

    f2, i2 = float64[:, ::1], int32[:, ::1]
    with device._uncontracted():
        ptx, _ = cuda.compile_ptx(run, (f2, f2, i2, f2, i2), device=False, cc=(9, 0))
    return ptx


def pair_loop(ptx: str) -> list[str]:
    """The instructions of the innermost loop that takes a square root (the pair loop): the
    shortest span from a label to a branch back to it holding ``sqrt.rn.f64``."""
    lines = [ln.strip() for ln in ptx.splitlines()]
    labels = {ln[:-1]: k for k, ln in enumerate(lines) if re.fullmatch(r"\$L__BB\d+_\d+:", ln)}
    best = None
    for k, ln in enumerate(lines):
        m = re.match(r"(?:@%p\d+ )?bra(?:\.uni)?\s+(\$L__BB\d+_\d+);", ln)
        if not m or m.group(1) not in labels or labels[m.group(1)] > k:
            continue
        body = lines[labels[m.group(1)]:k + 1]
        if any("sqrt.rn.f64" in b for b in body) and (best is None or len(body) < len(best)):
            best = body
    if best is None:
        return []
    return [b for b in best if b and not b.endswith(":") and not b.startswith(("//", "{", "}", "."))]


def _version(ptxas):
    out = subprocess.run([ptxas, "--version"], capture_output=True, text=True).stdout
    m = re.search(r"release (\d+)\.(\d+)", out)
    return (int(m.group(1)), int(m.group(2))) if m else None


def assemble(ptxas: str, ptx: str, max_registers: int) -> dict:
    """``ptxas -v`` at ``max_registers``: registers, spills, stack and shared memory."""
    ver = _version(ptxas)
    have = re.search(r"^\.version (\d+)\.(\d+)", ptx, flags=re.M)
    if ver is not None and ver[0] >= 13 and have is not None:  # PTX ISA 9.x for CUDA 13.x
        isa = (ver[0] - 4, ver[1])
        if (int(have.group(1)), int(have.group(2))) > isa:
            ptx = ptx.replace(have.group(0), f".version {isa[0]}.{isa[1]}", 1)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "k.ptx"
        src.write_text(ptx)
        r = subprocess.run([ptxas, "-arch=sm_90", "-v", f"-maxrregcount={max_registers}", str(src),
                            "-o", str(Path(tmp) / "k.cubin")], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"ptxas failed: {r.stderr.strip()[-2000:]}")
    text = r.stderr
    entry = text[text.index("Compiling entry function"):]
    used = re.search(r"Used (\d+) registers.*?(\d+) bytes smem", entry)
    spill = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads",
                      entry)
    return {"max_registers": max_registers, "registers": int(used.group(1)),
            "shared_bytes": int(used.group(2)), "stack_bytes": int(spill.group(1)),
            "spill_store_bytes": int(spill.group(2)), "spill_load_bytes": int(spill.group(3))}


def occupancy(nt: int, registers: int, shared: int) -> dict:
    """Blocks and warps of ``nt`` threads an sm_90 SM holds (the occupancy calculator's rules)."""
    warps = -(-nt // 32)
    per_warp = -(-registers * 32 // SM90["unit"]) * SM90["unit"]
    by_regs = SM90["registers"] // (per_warp * warps)
    by_threads = SM90["threads"] // nt
    by_shared = SM90["shared"] // max(shared + 1024, 1)  # (1 KiB reserved per block)
    blocks = min(by_regs, by_threads, by_shared, SM90["blocks"])
    return {"blocks_per_sm": blocks, "warps_per_sm": blocks * warps,
            "occupancy": blocks * warps / (SM90["threads"] // 32)}


def bounds_for(nt: int) -> list[int]:
    """Register bounds that let 1, 2 (and 4) blocks of ``nt`` threads fit an SM."""
    out = []
    for blocks in (1, 2, 4):
        b = min(255, SM90["registers"] // (nt * blocks) // 8 * 8)
        if b >= 32 and b not in out:
            out.append(b)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, nargs="*", default=[256, 512, 1024])
    ap.add_argument("--exponent", type=float, default=2.0, help="2.0, 2.5, or 0 for any")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    ptxas = find_ptxas()
    if ptxas is None:
        print("gpu_ptx: no ptxas (set PTXAS, or pip install '.[cuda]')", file=sys.stderr)
        return 2
    exponent = a.exponent or None
    t0 = time.perf_counter()
    loop = pair_loop(forces_ptx(exponent))
    rows = []
    print(f"gpu_ptx: {ptxas} ({'.'.join(map(str, _version(ptxas) or ()))}), exponent {exponent}")
    print(f"forces: {len(loop)} PTX instructions per pair (the innermost loop), "
          f"{sum('ld.global' in x for x in loop)} global loads, "
          f"{sum(x.startswith(('add.rn', 'sub.rn', 'mul.rn', 'div.rn', 'sqrt.rn')) for x in loop)} "
          "float64 operations")
    print(f"{'threads':>7} {'bound':>5} {'regs':>5} {'spill st':>8} {'spill ld':>8} {'stack':>5} "
          f"{'smem':>6} {'blocks/SM':>9} {'warps/SM':>8}")
    for nt in a.threads:
        ptx = kernel_ptx(nt, exponent)
        for bound in bounds_for(nt):
            r = assemble(ptxas, ptx, bound)
            r.update(threads=nt, **occupancy(nt, r["registers"], r["shared_bytes"]))
            rows.append(r)
            print(f"{nt:7d} {bound:5d} {r['registers']:5d} {r['spill_store_bytes']:8d} "
                  f"{r['spill_load_bytes']:8d} {r['stack_bytes']:5d} {r['shared_bytes']:6d} "
                  f"{r['blocks_per_sm']:9d} {r['warps_per_sm']:8d}", flush=True)
    print(f"gpu_ptx: {time.perf_counter() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps({"ptxas": ptxas, "exponent": exponent,
                                            "pair_loop_instructions": len(loop),
                                            "pair_loop": loop, "kernels": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
