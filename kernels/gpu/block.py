"""One packing's whole O'Hern search in one thread block: the block's phases, written once.

A GPU runs hundreds of packings at once, one thread block each (``kernels.gpu.batch``). Inside a
block, ``nt`` threads (a power of two) share the disks: thread ``t`` handles disks ``t, t + nt,
t + 2 nt, ...`` in every *phase* (forces, FIRE's move, the neighbour list's rebuild, the
rattler rounds of the residual). Between phases the threads meet at a barrier.

The search is a loop of *commands* (``C_*``), each a phase run by every thread, after which
thread 0 alone runs the *control* (``kernels.gpu.control``) (FIRE's adaptation, the convergence tests, the O'Hern search's
next radius scale: ``kernels.rules``) on the phase's block sums and writes the next command and
its scalars into the block's state ``sh`` (shared memory on the GPU); a barrier, and every
thread reads them. The search's whole scalar state lives in ``sh``, never in a thread's
registers: the hot phases hold only their own loop's values (few registers per thread, so more
threads per SM), and the state is one row of float64 that a launch loads at its start and
stores at its end (``st``). A search can therefore stop at a step budget and go on in a later
launch with the bits of an uninterrupted run (``C_SUSPEND``; see *Stop and go* below).

One FIRE step is two phases and one block reduction:

* ``C_STEP`` (the move): ``v += dt F``, FIRE's mixing ``v = (1 - a) v + mix F``, ``x += dt v``
  (after half a step back and ``v = 0`` when the last power was not positive); a thread whose
  disk moved more than half the skin since the lists were built raises the rebuild flag; a
  barrier; the lists rebuilt when the flag is up; then
* the forces, and in the same pass the sums FIRE and its tests need: energy, contacts and their
  force, ``|F|^2``, the power ``F.v`` and ``|v|^2`` (sums) and the largest ``|F|^2`` (max), in
  one reduction. ``|v + dt F|^2``, which FIRE's mixing needs after the kick, is then
  ``|v|^2 + 2 dt F.v + dt^2 |F|^2`` (``dt^2 |F|^2`` after a retreat): no second pass.

The virial is computed once per minimisation, at its end (``C_VIRIAL``); the rattler-aware
residual every ``CHECK_EVERY`` steps and when the cheap bound passes (``C_RESIDUAL``).

Block sums in a fixed order, the same on every target: each warp of 32 threads (or the block,
when smaller) sums its threads' partials in a tree (offsets 16, 8, 4, 2, 1), then the first warp
sums the warps' results in a tree. The code is compiled three ways from this source
(``make_block(jit, sync, slot_add, put, total, now, exponent)``):

* for the GPU: ``numba.cuda.jit(device=True)``; ``sync`` = ``cuda.syncthreads``; ``put`` sums
  a warp with shuffles (``shfl_down_sync``) and its lane 0 writes the warp's result; ``total``
  sums the warps' results in the first warp (``kernels.gpu.device``); each thread calls with
  ``t0 = threadIdx.x``, ``t1 = t0 + 1``: every loop ``for t in range(t0, t1)`` is its own part;
* for numba's CUDA simulator: the same kernel, with ``put`` writing each thread's partial to
  shared memory and ``total`` the trees over them between barriers (``put_shared``,
  ``total_shared`` below; the simulator has no shuffles);
* for the CPU emulation: ``numba.njit``, ``sync`` a no-op, called once with ``t0 = 0, t1 = nt``:
  every phase loops over all the threads' parts in turn before the next starts, which is what
  the barrier guarantees on the GPU; ``put_shared`` and ``total_shared`` again.

The three do the same floating-point operations in the same order (the trees, each thread's
strided disks, the neighbour rows sorted by index, no contraction: ``kernels.gpu.device``), so
the emulation gives the GPU's bits: whole packings are testable without a GPU.

Determinism: no atomics in any sum. The one atomic operation allocates a disk's slot in its
cell; each cell's members are then sorted by index, and each neighbour row is built in index
order, so the lists (and every sum over them) do not depend on thread timing. Flags that many
threads may raise (the rebuild) are written with the same value by all of them.

The potential's exponent is fixed when the block is compiled (``exponent``: 2.0, the harmonic
spring, and 2.5, Hertz, without ``pow``; ``None`` any exponent of the packing's parameters).

Stop and go: ``prm[P_BUDGET]`` bounds the FIRE steps of one launch. A search that reaches it
stops at the top of a FIRE step (its forces just computed and counted) with command
``C_SUSPEND``; its state row ``st`` and the arrays ``xy`` (positions), ``VX, VY`` and ``RX, RY``
(positions at the lists' build) are all it needs to go on: the next launch sets the radii from
the scale, rebuilds the neighbour rows from ``RX, RY`` (a row is every disk within contact plus
the skin of those positions, in increasing index: the same rows), recomputes the forces (the
same bits, not counted again) and continues, so that the packing ends with the bits of an
uninterrupted search (``tests/kernels/test_gpu.py``).

Differences from the CPU search (``kernels.protocol``), which make a GPU packing another
trajectory than the CPU packing of the same seed (hence its own task id, protocol key
``device: gpu``): full neighbour rows (each pair evaluated from both sides, the force on a disk
summed over its own row; the energy, contact count and force sums over both sides, halved),
the disks kept in the order the host gives (the host sorts the random start by cell once; the
CPU search re-sorts after its first minimisation), the mean diameter of the time step taken as
``scale`` times the initial one, the residual's forces those of the last FIRE step, and FIRE's
``|v|^2`` after the kick from the block's sums (above). The rules (FIRE 2.0, the search, the
convergence test, rattlers) are the CPU's.

Per-packing arrays (views of the batch's arrays, ``kernels.gpu.batch``; their rows, the state's
and the parameters' in ``kernels.gpu.state``): ``xy`` (n, 2) float64,
the positions (a neighbour's x and y in one 16-byte word); ``fl`` (8, n) float64, the rows
``VX, VY`` (velocities), ``FX, FY`` (forces), ``RX, RY`` (positions at the lists' build), ``R0``
(radii at scale 1), ``R`` (radii); ``nbr`` (MAXNB, n) int32 and ``ninv`` (MAXNB, n) float64:
slot ``k`` of every disk's neighbour row and its ``1 / (r_i + r_j)`` (slot-major, so that the
threads of a warp read consecutive words); ``iv`` (4, n) int32, the rows ``NNB`` (neighbours),
``CELL`` (a disk's cell), ``ALIVE, ALIVE2`` (the rattler rounds); ``cells`` (CAP + 1, C) int32:
row 0 the count of each cell, rows 1..CAP its members; ``red`` the reduction's scratch (shared
memory on the GPU); ``sh`` (N_ST) float64 the block's state (shared memory on the GPU); ``prm``
the packing's float64 parameters (``P_*``); ``st`` (N_ST) its state between launches, and its
results (``S_*``).
"""

import math
from types import SimpleNamespace

import numpy as np

from kernels.gpu.control import make_control
from kernels.gpu.state import (ALIVE, ALIVE2, CELL, C_BEGIN, C_DONE, C_RESIDUAL, C_RESUME,
                               C_START, C_STEP, C_SUSPEND, EV_FORCES, EV_OVERFLOW,
                               EV_RESIDUAL, EV_RESUMED, EV_START, EV_VIRIAL, EXPONENTS, FX, FY,
                               NNB, N_ST, P_ALPHA, P_BUDGET, P_LX, P_LY, P_NCX, P_NCY, P_SIN_TOL,
                               P_XY, R, R0, RX, RY, S_A, S_ALPHA, S_BUDGET, S_BUSY, S_CMD,
                               S_DT, S_HALF2, S_LAUNCHES, S_LSTEPS, S_LX, S_LY, S_MIX, S_NCX,
                               S_NCY, S_NG, S_RB, S_RESV, S_RETREAT, S_RMAX, S_SCALE, S_SIN_TOL,
                               S_SKIN, S_TE, S_TW, S_T_END, S_T_FIRST, S_T_LAUNCH, S_X0, S_X1,
                               S_X2, S_XY, VX, VY, WARP)
from kernels.space import fold_py, near_image_py


def pair_for(exponent):
    """The pair energy and force ``(V, f)`` at distance ``r`` given ``q = 1 / (r_i + r_j)``
    (``kernels.potential.pair_energy_force_py``'s formulas, the same bits) with the exponent
    fixed: 2.0 and 2.5 without ``pow``, ``None`` for any ``alpha``."""
    if exponent == 2.0:
        def pair(r, q, alpha):
            x = 1.0 - r * q
            if x <= 0.0:
                return 0.0, 0.0
            return 0.5 * x * x, x * q
    elif exponent == 2.5:
        def pair(r, q, alpha):
            x = 1.0 - r * q
            if x <= 0.0:
                return 0.0, 0.0
            xs = x * math.sqrt(x)
            return 0.4 * x * xs, xs * q
    elif exponent is None:
        def pair(r, q, alpha):
            x = 1.0 - r * q
            if x <= 0.0:
                return 0.0, 0.0
            xa1 = x ** (alpha - 1.0)
            return x * xa1 / alpha, xa1 * q
    else:
        raise ValueError(f"exponent: expected one of {EXPONENTS}, got {exponent!r}")
    return pair


def make_shared_reduction(jit, sync):
    """``put`` and ``total`` through a (ROWS, nt) array: each thread's partial in its column,
    then the trees (in each warp, then over the warps' results) level by level between
    barriers. The CPU emulation's and the CUDA simulator's (the GPU's are shuffles,
    ``kernels.gpu.device``; the same order of operations)."""

    @jit
    def put_sum(red, k, t, v):
        red[k, t] = v

    @jit
    def total(t0, t1, nt, red, sh, out, nsum, nmax):
        """Rows ``0 .. nsum - 1`` summed, the next ``nmax`` rows maxed; thread 0 writes them to
        ``sh[out ...]``. No barrier after: the callers meet one before reading them."""
        sync()
        w = WARP if nt >= WARP else nt
        s = w // 2
        while s > 0:
            for t in range(t0, t1):
                if t % w < s:
                    for k in range(nsum):
                        red[k, t] += red[k, t + s]
                    for k in range(nsum, nsum + nmax):
                        if red[k, t + s] > red[k, t]:
                            red[k, t] = red[k, t + s]
            sync()
            s = s // 2
        s = (nt // w) // 2
        while s > 0:
            for t in range(t0, t1):
                if t % w == 0 and t // w < s:
                    u = t + s * w
                    for k in range(nsum):
                        red[k, t] += red[k, u]
                    for k in range(nsum, nsum + nmax):
                        if red[k, u] > red[k, t]:
                            red[k, t] = red[k, u]
            sync()
            s = s // 2
        if t0 == 0:
            for k in range(nsum + nmax):
                sh[out + k] = red[k, 0]

    return put_sum, put_sum, total


def make_block(jit, sync, slot_add, put_sum, put_max, total, now, exponent):
    """The block's phases and its O'Hern search compiled with ``jit`` (see the module
    docstring). Returns them as a namespace: ``search``, the search of one packing,

    ``search(t0, t1, nt, xy, fl, nbr, ninv, iv, cells, red, sh, prm, st)``,

    and the phases it is made of (``forces``, ``move``, ``rebuild``, ``residual``, ``virial``),
    the ``control`` and the ``pair`` energy and force they call, as compiled.
    ``slot_add(cells, c)`` takes the next slot of cell ``c`` (``cells[0, c] += 1``, returning the
    old count); ``put_sum(red, k, t, v)`` and ``put_max`` give thread ``t``'s partial of row ``k``
    (called by every thread, in the same order); ``total(t0, t1, nt, red, sh, out, nsum, nmax)``
    completes the rows and thread 0 writes them to ``sh[out ...]``; ``now()`` the device's clock
    in ns (0 where the caller keeps time)."""
    pair = jit(pair_for(exponent))
    near = jit(near_image_py)
    fold = jit(fold_py)
    control = make_control(jit).control

    @jit
    def forces(t0, t1, nt, xy, fl, nbr, ninv, iv, red, sh):
        """Net forces and, in the same pass, the step's sums (each pair from both sides) to
        ``sh[S_TE ...]``: energy, contacts, their force, |F|^2, F.v, |v|^2, max |F|^2."""
        n = xy.shape[0]
        Lx = sh[S_LX]
        Ly = sh[S_LY]
        tilt = sh[S_XY] * Ly
        alpha = sh[S_ALPHA]
        hx = 0.5 * Lx
        hy = 0.5 * Ly
        for t in range(t0, t1):
            e = 0.0
            nc = 0.0
            fs = 0.0
            ff = 0.0
            p = 0.0
            vv = 0.0
            fm = 0.0
            for i0 in range(t, n, nt):
                i = np.uint32(i0)  # (unsigned indices: no wraparound for negative ones)
                xi = xy[i, 0]
                yi = xy[i, 1]
                fx = 0.0
                fy = 0.0
                for k0 in range(iv[NNB, i]):
                    k = np.uint32(k0)
                    j = np.uint32(nbr[k, i])
                    dx, dy = near(xy[j, 0] - xi, xy[j, 1] - yi, Lx, Ly, tilt, hx, hy)
                    d2 = dx * dx + dy * dy
                    q = ninv[k, i]
                    if d2 * q * q < 1.0:
                        r = math.sqrt(d2)
                        v, f = pair(r, q, alpha)
                        e += v
                        nc += 1.0
                        fs += f
                        if r > 0.0:
                            fr = f / r
                            fx -= fr * dx
                            fy -= fr * dy
                fl[FX, i] = fx
                fl[FY, i] = fy
                vx = fl[VX, i]
                vy = fl[VY, i]
                f2 = fx * fx + fy * fy
                ff += f2
                p += fx * vx + fy * vy
                vv += vx * vx + vy * vy
                if f2 > fm:
                    fm = f2
            put_sum(red, 0, t, e)
            put_sum(red, 1, t, nc)
            put_sum(red, 2, t, fs)
            put_sum(red, 3, t, ff)
            put_sum(red, 4, t, p)
            put_sum(red, 5, t, vv)
            put_max(red, 6, t, fm)
        total(t0, t1, nt, red, sh, S_TE, 6, 1)

    @jit
    def virial(t0, t1, nt, xy, nbr, ninv, iv, red, sh):
        """The virial ``sum r f`` over the contacts, each from both sides, to ``sh[S_TW]``."""
        n = xy.shape[0]
        Lx = sh[S_LX]
        Ly = sh[S_LY]
        tilt = sh[S_XY] * Ly
        alpha = sh[S_ALPHA]
        hx = 0.5 * Lx
        hy = 0.5 * Ly
        for t in range(t0, t1):
            w = 0.0
            for i0 in range(t, n, nt):
                i = np.uint32(i0)
                for k0 in range(iv[NNB, i]):
                    k = np.uint32(k0)
                    j = np.uint32(nbr[k, i])
                    dx, dy = near(xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1], Lx, Ly, tilt, hx, hy)
                    d2 = dx * dx + dy * dy
                    q = ninv[k, i]
                    if d2 * q * q < 1.0:
                        r = math.sqrt(d2)
                        w += r * pair(r, q, alpha)[1]
            put_sum(red, 0, t, w)
        total(t0, t1, nt, red, sh, S_TW, 1, 0)

    @jit
    def move(t0, t1, nt, xy, fl, sh):
        """FIRE's move with the step's ``dt``, ``a`` and ``mix`` (after half a step back and
        ``v = 0`` when told to retreat); raises the rebuild flag ``sh[S_RB]`` when a disk moved
        more than half the skin since the lists were built."""
        n = xy.shape[0]
        dt = sh[S_DT]
        a = sh[S_A]
        mix = sh[S_MIX]
        retreat = sh[S_RETREAT] != 0.0
        half2 = sh[S_HALF2]
        for t in range(t0, t1):
            far = False
            for i0 in range(t, n, nt):
                i = np.uint32(i0)
                x = xy[i, 0]
                y = xy[i, 1]
                vx = fl[VX, i]
                vy = fl[VY, i]
                fx = fl[FX, i]
                fy = fl[FY, i]
                if retreat:
                    x -= 0.5 * dt * vx
                    y -= 0.5 * dt * vy
                    vx = 0.0
                    vy = 0.0
                vx += dt * fx
                vy += dt * fy
                vx = (1.0 - a) * vx + mix * fx
                vy = (1.0 - a) * vy + mix * fy
                x += dt * vx
                y += dt * vy
                xy[i, 0] = x
                xy[i, 1] = y
                fl[VX, i] = vx
                fl[VY, i] = vy
                ddx = x - fl[RX, i]
                ddy = y - fl[RY, i]
                if ddx * ddx + ddy * ddy > half2:
                    far = True
            if far:
                sh[S_RB] = 1.0

    @jit
    def rebuild(t0, t1, nt, xy, fl, nbr, ninv, iv, cells, red, sh, wrap):
        """The neighbour rows: every ``j != i`` within ``r_i + r_j + skin`` of the positions
        ``RX, RY`` (nearest image), in increasing ``j``, from a cell list of cells at least
        ``2 rmax + skin`` wide. With ``wrap`` the positions are first folded into the cell and
        recorded in ``RX, RY``; without, the rows are rebuilt from the recorded ones (a search
        going on after a suspension). Returns False (to every thread) when a cell or a row
        outgrew its slots."""
        n = xy.shape[0]
        cap = cells.shape[0] - 1
        maxnb = nbr.shape[0]
        Lx = sh[S_LX]
        Ly = sh[S_LY]
        xyt = sh[S_XY]
        tilt = xyt * Ly
        skin = sh[S_SKIN]
        ncx = int(sh[S_NCX])
        ncy = int(sh[S_NCY])
        hx = 0.5 * Lx
        hy = 0.5 * Ly
        cutoff = 2.0 * sh[S_RMAX] + skin
        wx = Lx / math.sqrt(1.0 + xyt * xyt)
        nx = int(wx / cutoff)
        ny = int(Ly / cutoff)
        if nx > ncx:
            nx = ncx
        if ny > ncy:
            ny = ncy
        if nx < 3:
            nx = 1
        if ny < 3:
            ny = 1
        ncell = nx * ny
        for t in range(t0, t1):
            for c in range(t, ncell, nt):
                cells[0, c] = 0
            for i in range(t, n, nt):
                if wrap:
                    x, y = fold(xy[i, 0], xy[i, 1], Lx, Ly, tilt)
                    xy[i, 0] = x
                    xy[i, 1] = y
                    fl[RX, i] = x
                    fl[RY, i] = y
                else:
                    x = fl[RX, i]
                    y = fl[RY, i]
                # the cell's own (sheared) coordinates: x - xy y along a, y along b
                u = x - xyt * y
                u = u - Lx * math.floor(u / Lx)
                cx = min(max(int(u / Lx * nx), 0), nx - 1)
                cy = min(max(int(y / Ly * ny), 0), ny - 1)
                iv[CELL, i] = cx * ny + cy
        sync()
        for t in range(t0, t1):
            for i in range(t, n, nt):
                c = iv[CELL, i]
                s = slot_add(cells, c)
                if s < cap:
                    cells[1 + s, c] = i
        sync()
        for t in range(t0, t1):
            # each cell's members in increasing index (the slots were taken in any order)
            for c in range(t, ncell, nt):
                m = min(cells[0, c], cap)
                for a in range(2, m + 1):
                    v = cells[a, c]
                    b = a - 1
                    while b >= 1 and cells[b, c] > v:
                        cells[b + 1, c] = cells[b, c]
                        b -= 1
                    cells[b + 1, c] = v
        sync()
        for t in range(t0, t1):
            over = 0.0
            for i in range(t, n, nt):
                xi = fl[RX, i]
                yi = fl[RY, i]
                ri = fl[R, i]
                ci = iv[CELL, i]
                if cells[0, ci] > cap:
                    over = 1.0  # the disk's own cell outgrew its slots
                cx = ci // ny
                cy = ci - cx * ny
                m = 0
                for a in range(3 if nx >= 3 else 1):
                    gx = (cx + a - 1) % nx if nx >= 3 else 0
                    for b in range(3 if ny >= 3 else 1):
                        gy = (cy + b - 1) % ny if ny >= 3 else 0
                        g = gx * ny + gy
                        for s in range(1, min(cells[0, g], cap) + 1):
                            j = cells[s, g]
                            if j == i:
                                continue
                            dx, dy = near(fl[RX, j] - xi, fl[RY, j] - yi, Lx, Ly, tilt, hx, hy)
                            rc = ri + fl[R, j] + skin
                            if dx * dx + dy * dy < rc * rc:
                                if m >= maxnb:
                                    over = 1.0
                                    continue
                                # insert j in the row, kept in increasing index
                                u = m - 1
                                while u >= 0 and nbr[u, i] > j:
                                    nbr[u + 1, i] = nbr[u, i]
                                    ninv[u + 1, i] = ninv[u, i]
                                    u -= 1
                                nbr[u + 1, i] = j
                                ninv[u + 1, i] = 1.0 / (ri + fl[R, j])
                                m += 1
                iv[NNB, i] = m
            put_max(red, 0, t, over)
        total(t0, t1, nt, red, sh, S_X0, 0, 1)
        sync()
        # (S_X0 is next written by a total, after its barrier: every thread has read it)
        return sh[S_X0] == 0.0

    @jit
    def contact(i, k, xy, fl, nbr, Lx, Ly, tilt):
        """Slot ``k`` of disk ``i``'s row: the distance squared, whether the disks touch, and the
        unit vector from ``i`` to the neighbour (zero for coincident centres)."""
        j = nbr[k, i]
        dx, dy = near(xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1], Lx, Ly, tilt, 0.5 * Lx, 0.5 * Ly)
        s = fl[R, i] + fl[R, j]
        d2 = dx * dx + dy * dy
        d = math.sqrt(d2)
        if d > 0.0:
            return d2, d2 < s * s, dx / d, dy / d
        return d2, d2 < s * s, 0.0, 0.0

    @jit
    def load_bearing(i, xy, fl, nbr, iv, Lx, Ly, tilt, sin_tol):
        """``kernels.network._load_bearing`` for disk ``i`` among the ``ALIVE`` disks: at least 3
        contacts and no closed half-plane through its centre holding all of them."""
        z = 0
        for k in range(iv[NNB, i]):
            if iv[ALIVE, nbr[k, i]] != 0 and contact(i, k, xy, fl, nbr, Lx, Ly, tilt)[1]:
                z += 1
        if z < 3:
            return False
        for k in range(iv[NNB, i]):
            if iv[ALIVE, nbr[k, i]] == 0:
                continue
            _, touch, ux, uy = contact(i, k, xy, fl, nbr, Lx, Ly, tilt)
            if not touch:
                continue
            all_left = True
            for l in range(iv[NNB, i]):
                if l == k or iv[ALIVE, nbr[l, i]] == 0:
                    continue
                _, touch2, vx, vy = contact(i, l, xy, fl, nbr, Lx, Ly, tilt)
                if not touch2:
                    continue
                if ux * vy - uy * vx < -sin_tol:
                    all_left = False
                    break
            if all_left:
                return False
        return True

    @jit
    def residual(t0, t1, nt, xy, fl, nbr, ninv, iv, red, sh):
        """The force residual on non-rattlers (``kernels.minimiser._residual_core``) from the
        current forces: rattlers removed in rounds (a disk goes when it is not load-bearing
        among the disks alive in the previous round; the surviving set does not depend on the
        order), then ``max |F|`` over non-rattlers over the mean force of their contacts.
        Writes ``sh[S_RESV]`` (the residual) and ``sh[S_NG]`` (non-rattlers) by thread 0."""
        n = xy.shape[0]
        Lx = sh[S_LX]
        Ly = sh[S_LY]
        tilt = sh[S_XY] * Ly
        sin_tol = sh[S_SIN_TOL]
        alpha = sh[S_ALPHA]
        for t in range(t0, t1):
            for i in range(t, n, nt):
                iv[ALIVE, i] = 1
        sync()
        while True:
            for t in range(t0, t1):
                changed = 0.0
                ng = 0.0
                for i in range(t, n, nt):
                    keep = 0
                    if iv[ALIVE, i] != 0:
                        if load_bearing(i, xy, fl, nbr, iv, Lx, Ly, tilt, sin_tol):
                            keep = 1
                            ng += 1.0
                        else:
                            changed = 1.0
                    iv[ALIVE2, i] = keep
                put_sum(red, 0, t, ng)
                put_max(red, 1, t, changed)
            total(t0, t1, nt, red, sh, S_X0, 1, 1)
            sync()
            ng = sh[S_X0]
            changed_any = sh[S_X1] != 0.0
            for t in range(t0, t1):
                for i in range(t, n, nt):
                    iv[ALIVE, i] = iv[ALIVE2, i]
            sync()
            if not changed_any:
                break
        use_all = ng == 0.0
        for t in range(t0, t1):
            fs = 0.0
            nc = 0.0
            fm = 0.0
            for i in range(t, n, nt):
                for k in range(iv[NNB, i]):
                    j = nbr[k, i]
                    if j < i or not (use_all or (iv[ALIVE, i] != 0 and iv[ALIVE, j] != 0)):
                        continue
                    d2, touch, _, _ = contact(i, k, xy, fl, nbr, Lx, Ly, tilt)
                    if touch:
                        fs += pair(math.sqrt(d2), ninv[k, i], alpha)[1]
                        nc += 1.0
                if use_all or iv[ALIVE, i] != 0:
                    f2 = fl[FX, i] * fl[FX, i] + fl[FY, i] * fl[FY, i]
                    if f2 > fm:
                        fm = f2
            put_sum(red, 0, t, fs)
            put_sum(red, 1, t, nc)
            put_max(red, 2, t, fm)
        total(t0, t1, nt, red, sh, S_X0, 2, 1)
        if t0 == 0:
            fs = sh[S_X0]
            nc = sh[S_X1]
            fm = sh[S_X2]
            res = 0.0
            if nc != 0.0:
                mean = fs / nc
                if mean != 0.0:
                    res = math.sqrt(fm) / mean
            sh[S_RESV] = res
            sh[S_NG] = ng

    @jit
    def scale_radii(t0, t1, nt, fl, scale, zero_v):
        n = fl.shape[1]
        for t in range(t0, t1):
            for i in range(t, n, nt):
                fl[R, i] = scale * fl[R0, i]
                if zero_v:
                    fl[VX, i] = 0.0
                    fl[VY, i] = 0.0

    @jit
    def search(t0, t1, nt, xy, fl, nbr, ninv, iv, cells, red, sh, prm, st):
        """The O'Hern search of one packing (``kernels.protocol._ohern_search`` with FIRE) from
        its state ``st``, until it ends or its launch's step budget: radii scaled from ``R0``
        until a force-balanced minimum lands in ``[E_min, E_min (1 + window)]``; positions
        minimised in place (folded into the cell at the end), the state (and the results) in
        ``st``."""
        n = xy.shape[0]
        if t0 == 0:
            for k in range(N_ST):
                sh[k] = st[k]
            sh[S_LX] = prm[P_LX]
            sh[S_LY] = prm[P_LY]
            sh[S_XY] = prm[P_XY]
            sh[S_SIN_TOL] = prm[P_SIN_TOL]
            sh[S_NCX] = prm[P_NCX]
            sh[S_NCY] = prm[P_NCY]
            sh[S_ALPHA] = prm[P_ALPHA]
            sh[S_BUDGET] = prm[P_BUDGET]
            sh[S_LSTEPS] = 0.0
            sh[S_T_LAUNCH] = now()
            if sh[S_LAUNCHES] == 0.0:
                sh[S_T_FIRST] = sh[S_T_LAUNCH]
            sh[S_LAUNCHES] += 1.0
            if sh[S_CMD] == C_START:
                control(sh, prm, n, EV_START)
        sync()
        cmd = int(sh[S_CMD])
        if cmd == C_SUSPEND:
            cmd = C_RESUME
        while cmd != C_DONE and cmd != C_SUSPEND:
            event = EV_FORCES
            if cmd == C_STEP:
                move(t0, t1, nt, xy, fl, sh)
                sync()
                ok = True
                if sh[S_RB] != 0.0:
                    ok = rebuild(t0, t1, nt, xy, fl, nbr, ninv, iv, cells, red, sh, True)
                if ok:
                    forces(t0, t1, nt, xy, fl, nbr, ninv, iv, red, sh)
                else:
                    event = EV_OVERFLOW
            elif cmd == C_BEGIN or cmd == C_RESUME:
                scale_radii(t0, t1, nt, fl, sh[S_SCALE], cmd == C_BEGIN)
                sync()
                if rebuild(t0, t1, nt, xy, fl, nbr, ninv, iv, cells, red, sh, cmd == C_BEGIN):
                    forces(t0, t1, nt, xy, fl, nbr, ninv, iv, red, sh)
                    if cmd == C_RESUME:
                        event = EV_RESUMED
                else:
                    event = EV_OVERFLOW
            elif cmd == C_RESIDUAL:
                residual(t0, t1, nt, xy, fl, nbr, ninv, iv, red, sh)
                event = EV_RESIDUAL
            else:  # C_VIRIAL
                virial(t0, t1, nt, xy, nbr, ninv, iv, red, sh)
                event = EV_VIRIAL
            if t0 == 0:
                sh[S_RB] = 0.0
                control(sh, prm, n, event)
            sync()
            cmd = int(sh[S_CMD])
        if cmd == C_DONE:
            Lx = sh[S_LX]
            Ly = sh[S_LY]
            tilt = sh[S_XY] * Ly
            for t in range(t0, t1):
                for i in range(t, n, nt):
                    x, y = fold(xy[i, 0], xy[i, 1], Lx, Ly, tilt)
                    xy[i, 0] = x
                    xy[i, 1] = y
        if t0 == 0:
            end = now()
            sh[S_BUSY] += end - sh[S_T_LAUNCH]
            if cmd == C_DONE:
                sh[S_T_END] = end
            for k in range(N_ST):
                st[k] = sh[k]

    return SimpleNamespace(search=search, forces=forces, move=move, rebuild=rebuild,
                           residual=residual, virial=virial, control=control, pair=pair)
