"""One packing's whole O'Hern search in one thread block: the block's phases, written once.

A GPU runs hundreds of packings at once, one thread block each (``kernels.gpu.batch``). Inside a
block, ``nt`` threads (a power of two) share the disks: thread ``t`` handles disks ``t, t + nt,
t + 2 nt, ...`` in every *phase* (forces, FIRE's update, the neighbour list's rebuild, the
rattler rounds of the residual). Between phases the threads meet at a barrier. Scalars that
steer the search (the FIRE sums, the largest force, the energy) come from block reductions in a
fixed tree order; every thread then runs the same scalar logic (FIRE's adaptation, the search's
next radius scale: ``kernels.rules``) on the same values, so all threads agree without
broadcasting.

The code below is compiled twice from the same source by ``make_block(jit, sync, slot_add)``:

* for the GPU: ``jit = numba.cuda.jit(device=True)``, ``sync`` = ``cuda.syncthreads``,
  ``slot_add`` = ``cuda.atomic.add``; each thread calls the search with ``t0 = threadIdx.x``,
  ``t1 = t0 + 1``: every per-thread loop ``for t in range(t0, t1)`` is that thread's own part.
* for the CPU emulation: ``jit = numba.njit``, ``sync`` a no-op, ``slot_add`` a plain
  increment, called once with ``t0 = 0, t1 = nt``: every phase loops over all the threads'
  parts in turn before the next phase starts, which is what the barrier guarantees on the GPU.

Both do the same floating-point operations in the same order (the reductions' tree, each
thread's strided disks, the neighbour rows sorted by index), so the emulation gives the GPU's
bits up to the GPU compiler's fused multiply-adds: whole packings are testable without a GPU.

Determinism: no atomics in any sum. The one atomic operation allocates a disk's slot in its
cell; each cell's members are then sorted by index, and each neighbour row is built in index
order, so the lists (and every sum over them) do not depend on thread timing.

Differences from the CPU search (``kernels.protocol``), which make a GPU packing another
trajectory than the CPU packing of the same seed (hence its own task id, protocol key
``device: gpu``): full neighbour rows (each pair evaluated from both sides, the force on a disk
summed over its own row), the disks kept in the order the host gives (the host sorts the random
start by cell once; the CPU search re-sorts after its first minimisation), the mean diameter of
the time step taken as ``scale`` times the initial one, and the residual's forces those of the
last FIRE step. The rules (FIRE 2.0, the search, the convergence test, rattlers) are the CPU's.

Per-packing arrays (views of the batch's arrays, ``kernels.gpu.batch``), few and packed, because
every array a GPU thread holds costs registers (its shape and strides): ``fl`` (10, n) float64, the
rows ``X, Y`` (positions), ``VX, VY``, ``FX, FY``, ``RX, RY`` (positions at the lists' build),
``R0`` (radii at scale 1), ``R`` (radii); ``nbr`` (MAXNB, n) int32 and ``ninv`` (MAXNB, n)
float64: slot ``k`` of every disk's neighbour row and its ``1 / (r_i + r_j)`` (slot-major, so
that the threads of a warp read consecutive words); ``iv`` (4, n) int32, the rows ``NNB``
(neighbours), ``CELL`` (a disk's cell), ``ALIVE, ALIVE2`` (the rattler rounds); ``cells``
(CAP + 1, C) int32: row 0 the count of each cell, rows 1..CAP its members; ``red`` (8, nt)
float64 (shared memory on the GPU); ``prm`` the packing's float64 parameters (``P_*``); ``out``
its results (``O_*``).
"""

import math
from types import SimpleNamespace

from kernels import rules
from kernels.potential import pair_energy_force_py
from kernels.space import fold_py, near_image_py

# the search's settings, one float64 row per packing (prm)
P_E_MIN = 0
P_WINDOW = 1
P_TOL = 2
P_SEARCH_TOL = 3
P_MAX_SEARCH = 4
P_MAX_STEPS = 5
P_SKIN = 6  # in mean diameters
P_DELTA = 7
P_RULE = 8
P_MAX_RADIUS = 9
P_ENERGY_STEP = 10
P_ALPHA = 11
P_LX = 12
P_LY = 13
P_XY = 14
P_MEAN_D = 15  # mean diameter at scale 1
P_RMAX = 16  # largest radius at scale 1
P_SIN_TOL = 17  # the rattlers' half-plane slack, sin(HALF_PLANE_TOL)
P_NCX = 18  # cells allocated along x and y (the grid used is never finer)
P_NCY = 19
N_PARAMS = 20

# the results, one float64 row per packing (out)
O_STATUS = 0
O_SCALE = 1
O_ENERGY = 2
O_VIRIAL = 3
O_RESIDUAL = 4
O_ITERATIONS = 5
O_FORCE_EVALS = 6
O_STEPS = 7
N_OUT = 8

#: status of a packing whose cell or neighbour row outgrew its slots (kernels.jamming's codes
#: 0-4 are the CPU search's)
ST_OVERFLOW = 5

ROWS = 8  # rows of the reduction buffer red

# rows of fl and iv
X, Y, VX, VY, FX, FY, RX, RY, R0, R = range(10)
N_FL = 10
NNB, CELL, ALIVE, ALIVE2 = range(4)
N_IV = 4


def make_block(jit, sync, slot_add):
    """The block's phases and its O'Hern search compiled with ``jit`` (see the module
    docstring). Returns them as a namespace: ``ohern``, the search of one packing,

    ``ohern(t0, t1, nt, fl, nbr, ninv, iv, cells, red, prm, out)``, and the phases it is made of
    (``fire``, ``forces``, ``rebuild``, ``residual``); ``slot_add(cells, c)``
    takes the next slot of cell ``c`` (``cells[0, c] += 1``, returning the old count)."""
    pair = jit(pair_energy_force_py)
    near = jit(near_image_py)
    fold = jit(fold_py)
    fire_adapt = jit(rules.fire_adapt)
    dt_from_diameter = jit(rules.dt_from_diameter)
    search_step = jit(rules.search_step)
    search_targets = jit(rules.search_targets)
    search_start = jit(rules.search_start)

    @jit
    def reduce(t0, t1, nt, red, nsum, nmax):
        """Tree reduction of ``red``'s rows (each thread has written its partials in column
        ``t``): rows ``0 .. nsum - 1`` summed, the next ``nmax`` rows maxed, into column 0.
        Every thread reads the results after the call; the caller meets a barrier before
        writing ``red`` again."""
        sync()
        s = nt // 2
        while s > 0:
            for t in range(t0, t1):
                if t < s:
                    for k in range(nsum):
                        red[k, t] += red[k, t + s]
                    for k in range(nsum, nsum + nmax):
                        if red[k, t + s] > red[k, t]:
                            red[k, t] = red[k, t + s]
            sync()
            s = s // 2

    @jit
    def forces(t0, t1, nt, fl, nbr, ninv, iv, red, alpha, Lx, Ly, tilt):
        """Net forces, and the sums FIRE and its tests need: energy, virial, contacts and their
        force (each pair once), |F|^2, the power F.v (sums) and the largest |F|^2 (max).
        Returns ``(energy, virial, n_contacts, fsum, ff, p, fmax2)``."""
        n = fl.shape[1]
        hx = 0.5 * Lx
        hy = 0.5 * Ly
        for t in range(t0, t1):
            e = 0.0
            w = 0.0
            nc = 0.0
            fs = 0.0
            ff = 0.0
            p = 0.0
            fm = 0.0
            for i in range(t, n, nt):
                xi = fl[X, i]
                yi = fl[Y, i]
                fx = 0.0
                fy = 0.0
                for k in range(iv[NNB, i]):
                    j = nbr[k, i]
                    dx, dy = near(fl[X, j] - xi, fl[Y, j] - yi, Lx, Ly, tilt, hx, hy)
                    d2 = dx * dx + dy * dy
                    q = ninv[k, i]
                    if d2 * q * q >= 1.0:
                        continue
                    r = math.sqrt(d2)
                    v, f = pair(r, q, alpha)
                    if j > i:
                        e += v
                        w += r * f
                        nc += 1.0
                        fs += f
                    if r > 0.0:
                        fr = f / r
                        fx -= fr * dx
                        fy -= fr * dy
                fl[FX, i] = fx
                fl[FY, i] = fy
                f2 = fx * fx + fy * fy
                ff += f2
                p += fx * fl[VX, i] + fy * fl[VY, i]
                if f2 > fm:
                    fm = f2
            red[0, t] = e
            red[1, t] = w
            red[2, t] = nc
            red[3, t] = fs
            red[4, t] = ff
            red[5, t] = p
            red[6, t] = fm
        reduce(t0, t1, nt, red, 6, 1)
        out = (red[0, 0], red[1, 0], red[2, 0], red[3, 0], red[4, 0], red[5, 0], red[6, 0])
        sync()
        return out

    @jit
    def rebuild(t0, t1, nt, fl, nbr, ninv, iv, cells, red, Lx, Ly, xy, skin, rmax, ncx, ncy):
        """Wrap the positions, record them in ``RX, RY`` and rebuild the neighbour rows: every
        ``j != i`` within ``r_i + r_j + skin`` (nearest image), in increasing ``j``, from a cell
        list of cells at least ``2 rmax + skin`` wide. Returns False when a cell or a row
        outgrew its slots."""
        n = fl.shape[1]
        cap = cells.shape[0] - 1
        maxnb = nbr.shape[0]
        tilt = xy * Ly
        hx = 0.5 * Lx
        hy = 0.5 * Ly
        cutoff = 2.0 * rmax + skin
        wx = Lx / math.sqrt(1.0 + xy * xy)
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
                x, y = fold(fl[X, i], fl[Y, i], Lx, Ly, tilt)
                fl[X, i] = x
                fl[Y, i] = y
                fl[RX, i] = x
                fl[RY, i] = y
                # the cell's own (sheared) coordinates: x - xy y along a, y along b
                u = x - xy * y
                u = u - Lx * math.floor(u / Lx)
                cx = min(max(int(u / Lx * nx), 0), nx - 1)
                cy = min(max(int(y / Ly * ny), 0), ny - 1)
                iv[CELL, i] = cx * ny + cy
        sync()
        for t in range(t0, t1):
            over = 0.0
            for i in range(t, n, nt):
                c = iv[CELL, i]
                s = slot_add(cells, c)
                if s < cap:
                    cells[1 + s, c] = i
                else:
                    over = 1.0
            red[0, t] = over
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
            over = red[0, t]
            for i in range(t, n, nt):
                xi = fl[X, i]
                yi = fl[Y, i]
                ri = fl[R, i]
                ci = iv[CELL, i]
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
                            dx, dy = near(fl[X, j] - xi, fl[Y, j] - yi, Lx, Ly, tilt, hx, hy)
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
            red[0, t] = over
        reduce(t0, t1, nt, red, 0, 1)
        ok = red[0, 0] == 0.0
        sync()
        return ok

    @jit
    def contact(i, k, fl, nbr, Lx, Ly, tilt):
        """Slot ``k`` of disk ``i``'s row: the distance squared, whether the disks touch, and the
        unit vector from ``i`` to the neighbour (zero for coincident centres)."""
        j = nbr[k, i]
        dx, dy = near(fl[X, j] - fl[X, i], fl[Y, j] - fl[Y, i], Lx, Ly, tilt, 0.5 * Lx, 0.5 * Ly)
        s = fl[R, i] + fl[R, j]
        d2 = dx * dx + dy * dy
        d = math.sqrt(d2)
        if d > 0.0:
            return d2, d2 < s * s, dx / d, dy / d
        return d2, d2 < s * s, 0.0, 0.0

    @jit
    def load_bearing(i, fl, nbr, iv, Lx, Ly, tilt, sin_tol):
        """``kernels.network._load_bearing`` for disk ``i`` among the ``ALIVE`` disks: at least 3
        contacts and no closed half-plane through its centre holding all of them."""
        z = 0
        for k in range(iv[NNB, i]):
            if iv[ALIVE, nbr[k, i]] != 0 and contact(i, k, fl, nbr, Lx, Ly, tilt)[1]:
                z += 1
        if z < 3:
            return False
        for k in range(iv[NNB, i]):
            if iv[ALIVE, nbr[k, i]] == 0:
                continue
            _, touch, ux, uy = contact(i, k, fl, nbr, Lx, Ly, tilt)
            if not touch:
                continue
            all_left = True
            for l in range(iv[NNB, i]):
                if l == k or iv[ALIVE, nbr[l, i]] == 0:
                    continue
                _, touch2, vx, vy = contact(i, l, fl, nbr, Lx, Ly, tilt)
                if not touch2:
                    continue
                if ux * vy - uy * vx < -sin_tol:
                    all_left = False
                    break
            if all_left:
                return False
        return True

    @jit
    def residual(t0, t1, nt, fl, nbr, ninv, iv, red, alpha, Lx, Ly, tilt, sin_tol):
        """The force residual on non-rattlers (``kernels.minimiser._residual_core``) from the
        current forces: rattlers removed in rounds (a disk goes when it is not load-bearing
        among the disks alive in the previous round; the surviving set does not depend on the
        order), then ``max |F|`` over non-rattlers over the mean force of their contacts.
        Returns ``(residual, n_nonrattlers)``."""
        n = fl.shape[1]
        for t in range(t0, t1):
            for i in range(t, n, nt):
                iv[ALIVE, i] = 1
        sync()
        while True:
            for t in range(t0, t1):
                changed = 0.0
                for i in range(t, n, nt):
                    keep = 0
                    if iv[ALIVE, i] != 0:
                        if load_bearing(i, fl, nbr, iv, Lx, Ly, tilt, sin_tol):
                            keep = 1
                        else:
                            changed = 1.0
                    iv[ALIVE2, i] = keep
                red[0, t] = changed
            reduce(t0, t1, nt, red, 0, 1)
            changed_any = red[0, 0] != 0.0
            sync()
            for t in range(t0, t1):
                for i in range(t, n, nt):
                    iv[ALIVE, i] = iv[ALIVE2, i]
            sync()
            if not changed_any:
                break
        for t in range(t0, t1):
            ng = 0.0
            for i in range(t, n, nt):
                ng += iv[ALIVE, i]
            red[0, t] = ng
        reduce(t0, t1, nt, red, 1, 0)
        ng = red[0, 0]
        sync()
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
                    d2, touch, _, _ = contact(i, k, fl, nbr, Lx, Ly, tilt)
                    if touch:
                        fs += pair(math.sqrt(d2), ninv[k, i], alpha)[1]
                        nc += 1.0
                if use_all or iv[ALIVE, i] != 0:
                    f2 = fl[FX, i] * fl[FX, i] + fl[FY, i] * fl[FY, i]
                    if f2 > fm:
                        fm = f2
            red[0, t] = fs
            red[1, t] = nc
            red[2, t] = fm
        reduce(t0, t1, nt, red, 2, 1)
        fs = red[0, 0]
        nc = red[1, 0]
        fm = red[2, 0]
        sync()
        if nc == 0.0:
            return 0.0, ng
        mean = fs / nc
        if mean == 0.0:
            return 0.0, ng
        return math.sqrt(fm) / mean, ng

    @jit
    def fire(t0, t1, nt, fl, nbr, ninv, iv, cells, red, prm, tol, max_steps, skin, rmax, dt0,
             e_abort):
        """One FIRE 2.0 minimisation at fixed radii (``kernels.fire._fire_run`` from rest).
        Returns ``(status, steps, force_evaluations, energy, virial, residual)``; status
        ``ST_OVERFLOW`` when the lists outgrew their slots."""
        n = fl.shape[1]
        alpha = prm[P_ALPHA]
        Lx = prm[P_LX]
        Ly = prm[P_LY]
        xy = prm[P_XY]
        tilt = xy * Ly
        sin_tol = prm[P_SIN_TOL]
        ncx = int(prm[P_NCX])
        ncy = int(prm[P_NCY])
        dt_max = rules.DT_MAX_FACTOR * dt0
        dt_min = rules.DT_MIN_FACTOR * dt0
        dt = dt0
        a = rules.A_START
        n_pos = 0
        n_neg = 0
        for t in range(t0, t1):
            for i in range(t, n, nt):
                fl[VX, i] = 0.0
                fl[VY, i] = 0.0
        if not rebuild(t0, t1, nt, fl, nbr, ninv, iv, cells, red, Lx, Ly, xy, skin, rmax, ncx, ncy):
            return ST_OVERFLOW, 0, 0, 0.0, 0.0, math.inf
        half2 = 0.25 * skin * skin
        energy, virial, nc, fsum, ff, p, fmax2 = forces(t0, t1, nt, fl, nbr, ninv, iv, red, alpha,
                                                        Lx, Ly, tilt)
        nforce = 1
        status = rules.MAX_STEPS
        res = math.inf
        step = 0
        while True:
            if e_abort > 0.0 and energy < e_abort:
                status = rules.BELOW
                res = -1.0
                break
            if nc == 0.0:
                status = rules.CONVERGED
                res = 0.0
                break
            mean_f = fsum / nc
            bound = math.sqrt(fmax2) / mean_f if mean_f > 0.0 else 0.0
            if bound < tol or step % rules.CHECK_EVERY == 0 or step >= max_steps:
                res = residual(t0, t1, nt, fl, nbr, ninv, iv, red, alpha, Lx, Ly, tilt, sin_tol)[0]
                if res < tol:
                    status = rules.CONVERGED
                    break
            if step >= max_steps:
                status = rules.MAX_STEPS
                break
            step += 1
            n_pos, n_neg, dt, a = fire_adapt(p, step, n_pos, n_neg, dt, a, dt_min, dt_max)
            if p <= 0.0 and n_neg > rules.N_NEG_MAX:
                status = rules.STALLED
                res = residual(t0, t1, nt, fl, nbr, ninv, iv, red, alpha, Lx, Ly, tilt, sin_tol)[0]
                break
            # (retreat half a step and stop on a non-positive power), then v += dt F
            for t in range(t0, t1):
                vv = 0.0
                for i in range(t, n, nt):
                    if p <= 0.0:
                        fl[X, i] -= 0.5 * dt * fl[VX, i]
                        fl[Y, i] -= 0.5 * dt * fl[VY, i]
                        fl[VX, i] = 0.0
                        fl[VY, i] = 0.0
                    fl[VX, i] += dt * fl[FX, i]
                    fl[VY, i] += dt * fl[FY, i]
                    vv += fl[VX, i] * fl[VX, i] + fl[VY, i] * fl[VY, i]
                red[0, t] = vv
            reduce(t0, t1, nt, red, 1, 0)
            vv = red[0, 0]
            sync()
            mix = a * math.sqrt(vv / ff) if ff > 0.0 else 0.0
            # FIRE's mixing and the move; the largest displacement since the lists were built
            for t in range(t0, t1):
                disp2 = 0.0
                for i in range(t, n, nt):
                    fl[VX, i] = (1.0 - a) * fl[VX, i] + mix * fl[FX, i]
                    fl[VY, i] = (1.0 - a) * fl[VY, i] + mix * fl[FY, i]
                    fl[X, i] += dt * fl[VX, i]
                    fl[Y, i] += dt * fl[VY, i]
                    ddx = fl[X, i] - fl[RX, i]
                    ddy = fl[Y, i] - fl[RY, i]
                    d2 = ddx * ddx + ddy * ddy
                    if d2 > disp2:
                        disp2 = d2
                red[0, t] = disp2
            reduce(t0, t1, nt, red, 0, 1)
            disp2 = red[0, 0]
            sync()
            if disp2 > half2:
                if not rebuild(t0, t1, nt, fl, nbr, ninv, iv, cells, red, Lx, Ly, xy, skin, rmax,
                               ncx, ncy):
                    return ST_OVERFLOW, step, nforce, energy, virial, math.inf
            energy, virial, nc, fsum, ff, p, fmax2 = forces(t0, t1, nt, fl, nbr, ninv, iv, red,
                                                            alpha, Lx, Ly, tilt)
            nforce += 1
        return status, step, nforce, energy, virial, res

    @jit
    def ohern_block(t0, t1, nt, fl, nbr, ninv, iv, cells, red, prm, out):
        """The O'Hern search of one packing (``kernels.protocol._ohern_search`` with FIRE):
        radii scaled from ``R0`` until a force-balanced minimum lands in ``[E_min, E_min (1 +
        window)]``; positions minimised in place and left wrapped, results in ``out``."""
        n = fl.shape[1]
        e_min = prm[P_E_MIN]
        window = prm[P_WINDOW]
        tol = prm[P_TOL]
        search_tol = prm[P_SEARCH_TOL]
        max_search = int(prm[P_MAX_SEARCH])
        max_steps = int(prm[P_MAX_STEPS])
        skin_factor = prm[P_SKIN]
        delta0 = prm[P_DELTA]
        rule = int(prm[P_RULE])
        max_radius = prm[P_MAX_RADIUS]
        energy_step = prm[P_ENERGY_STEP]
        alpha = prm[P_ALPHA]
        mean_d = prm[P_MEAN_D]
        rmax0 = prm[P_RMAX]
        e_max, inv_a, g_target, x_per_g = search_targets(e_min, window, alpha)
        scale = 1.0
        delta, last_dir, s1, g1, s2, g2, slope, n_below = search_start(delta0)
        it = 0
        nforce = 0
        steps = 0
        status = 1  # max_search
        e_last = 0.0
        w_last = 0.0
        res_last = math.inf
        e_guess = max(e_min, rules.E_FIRST_GUESS)
        abort = rules.ABORT_FRACTION * e_min * n
        while True:
            it += 1
            for t in range(t0, t1):
                for i in range(t, n, nt):
                    fl[R, i] = scale * fl[R0, i]
            sync()
            skin = skin_factor * mean_d * scale
            rmax = rmax0 * scale
            dt0 = dt_from_diameter(mean_d * scale, alpha, e_guess)
            st, nst, nf, e, w, res = fire(t0, t1, nt, fl, nbr, ninv, iv, cells, red, prm,
                                          search_tol, max_steps, skin, rmax, dt0, abort)
            nforce += nf
            steps += nst
            if (st == rules.CONVERGED and e_min <= e / n <= e_max and search_tol > tol):
                # polish to the final tolerance at the same radii
                st, nst, nf, e, w, res = fire(t0, t1, nt, fl, nbr, ninv, iv, cells, red, prm, tol,
                                              max_steps, skin, rmax, dt0, abort)
                nforce += nf
                steps += nst
            e_last = e
            w_last = w
            res_last = res
            eg = e / n
            if st == ST_OVERFLOW:
                status = ST_OVERFLOW
                break
            if st == rules.CONVERGED and eg > 0.0:
                e_guess = eg
            if st == rules.MAX_STEPS:
                status = 2  # max_steps
                break
            if st != rules.CONVERGED and st != rules.BELOW:
                status = 3  # stalled
                break
            if st == rules.CONVERGED and e_min <= eg <= e_max:
                status = 0  # converged
                break
            if it >= max_search:
                status = 1  # max_search
                break
            new, delta, last_dir, s1, g1, s2, g2, slope, n_below = search_step(
                rule, st == rules.CONVERGED and eg > 0.0, st == rules.BELOW or eg < e_min, eg,
                scale, delta, last_dir, s1, g1, s2, g2, slope, n_below, delta0, g_target,
                x_per_g, inv_a, energy_step)
            if new == scale:
                status = 1  # max_search: the step is below the scale's float64 resolution
                break
            if new * rmax0 > max_radius:
                status = 4  # too_dense
                break
            scale = new
        Lx = prm[P_LX]
        Ly = prm[P_LY]
        tilt = prm[P_XY] * Ly
        for t in range(t0, t1):
            for i in range(t, n, nt):
                x, y = fold(fl[X, i], fl[Y, i], Lx, Ly, tilt)
                fl[X, i] = x
                fl[Y, i] = y
        sync()
        if t0 == 0:
            out[O_STATUS] = status
            out[O_SCALE] = scale
            out[O_ENERGY] = e_last
            out[O_VIRIAL] = w_last
            out[O_RESIDUAL] = res_last
            out[O_ITERATIONS] = it
            out[O_FORCE_EVALS] = nforce
            out[O_STEPS] = steps

    return SimpleNamespace(ohern=ohern_block, fire=fire, forces=forces, rebuild=rebuild,
                           residual=residual)
