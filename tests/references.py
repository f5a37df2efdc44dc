"""The tests' oracles: slow, obviously correct reference implementations, one name per meaning.

Every kernel is compared with one of these (plain loops over all pairs, dictionaries, scipy)
rather than with itself. Where two references measure the same thing differently, their names
say how (``ref_contact_pairs``: a list of pairs by loops; ``ref_contact_arrays``: arrays with
distances and contact distances, vectorised). No test module imports another: shared packing
makers and fakes are in ``helpers.py``.
"""

import math

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from kernels.potential import forces


#: The kernels' default slack of the half-plane rule (kernels.network.HALF_PLANE_TOL).
HALF_PLANE_SLACK = 1e-9 * math.pi


def in_closed_half_plane(angles, slack=HALF_PLANE_SLACK):
    """Do directions ``angles`` (radians) all lie in a closed half-plane? True when the
    largest angular gap between consecutive directions is at least ``pi - slack``."""
    a = sorted(x % (2 * math.pi) for x in angles)
    gaps = [b - c for c, b in zip(a, a[1:])] + [a[0] + 2 * math.pi - a[-1]]
    return max(gaps) >= math.pi - slack


def ref_nonrattlers(n, i, j, d, slack=HALF_PLANE_SLACK):
    """Keep the disks with at least 3 contacts among the kept ones, not all in a closed
    half-plane; repeat until nothing changes (sorted angles, plain loops). ``d[k]`` is the
    displacement from disk ``i[k]`` to disk ``j[k]``."""
    alive = np.ones(n, bool)
    while True:
        dirs = {g: [] for g in range(n) if alive[g]}
        for a, b, (x, y) in zip(i, j, d):
            if alive[a] and alive[b]:
                dirs[a].append(math.atan2(y, x))
                dirs[b].append(math.atan2(-y, -x))
        drop = [g for g, ang in dirs.items() if len(ang) < 3 or in_closed_half_plane(ang, slack)]
        if not drop:
            return alive
        alive[drop] = False


def ref_contact_pairs(pos, rad, box):
    out = []
    for i in range(len(pos)):
        for j in range(i + 1, len(pos)):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            if np.hypot(*d) < rad[i] + rad[j]:
                out.append((i, j))
    return out


def ref_contact_arrays(pos, rad, box):
    n = len(pos)
    d = pos[None, :, :] - pos[:, None, :]
    d -= box * np.round(d / box)
    r = np.hypot(d[..., 0], d[..., 1])
    s = rad[:, None] + rad[None, :]
    i, j = np.nonzero(np.triu(r < s, 1))
    return i, j, r[i, j], s[i, j]


def ref_contact_triples(pos, rad, box):
    """Every overlapping pair ``(i, j, d = r_j - r_i)`` (minimum image), brute force."""
    out = []
    n = len(rad)
    for i in range(n):
        for j in range(i + 1, n):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            if np.hypot(*d) < rad[i] + rad[j]:
                out.append((i, j, d))
    return out


def ref_candidate_pairs(pos, rad, box, skin):
    """Obviously correct: every pair, nearest image by explicit search over 5 x 5 images."""
    shifts = np.array([(a * box[0], b * box[1]) for a in range(-2, 3) for b in range(-2, 3)])
    out = []
    n = len(pos)
    for i in range(n - 1):
        d = pos[i + 1:, None, :] - pos[i] + shifts[None, :, :]  # (n-i-1, 25, 2)
        best = np.hypot(d[..., 0], d[..., 1]).min(axis=1)
        js = np.nonzero(best < rad[i] + rad[i + 1:] + skin)[0] + i + 1
        out.extend((i, int(j)) for j in js)
    return out


def ref_nearest_image(dx, dy, box):
    Lx, Ly, xy = box
    best = None
    for k in range(-3, 4):
        for m in range(-3, 4):
            v = np.array([dx + m * Lx + k * xy * Ly, dy + k * Ly])
            if best is None or v @ v < best @ best:
                best = v
    return best


def ref_nonrattler_mask(n, contacts, pos, box):
    i = [a for a, _ in contacts]
    j = [b for _, b in contacts]
    d = pos[j] - pos[i]
    d = d - box * np.round(d / box)
    return ref_nonrattlers(n, i, j, d)


def ref_kept_contacts(pos, rad, box):
    pairs = ref_contact_triples(pos, rad, box)
    alive = ref_nonrattlers(len(rad), [p[0] for p in pairs], [p[1] for p in pairs], [p[2] for p in pairs])
    return alive, [p for p in pairs if alive[p[0]] and alive[p[1]]]


def ref_energy(pos, rad, box, alpha):
    """Slow reference: explicit double loop, nearest image by rounding."""
    e = 0.0
    for i in range(len(pos)):
        for j in range(i + 1, len(pos)):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            r = np.hypot(*d)
            s = rad[i] + rad[j]
            if r < s:
                e += (1.0 - r / s) ** alpha / alpha
    return e


def ref_force_residual(pos, rad, box, alpha):
    c = ref_contact_pairs(pos, rad, box)
    keep = ref_nonrattler_mask(len(pos), c, pos, box)
    f = forces(pos, rad, box, alpha)
    fc = []
    for i, j in c:
        if keep[i] and keep[j]:
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            s = rad[i] + rad[j]
            fc.append((1 - np.hypot(*d) / s) ** (alpha - 1) / s)
    return np.max(np.hypot(f[keep, 0], f[keep, 1])) / np.mean(fc), keep


def ref_packing_measures(p):
    """Independent E_G, force residual on non-rattlers, N_G and contacts among them."""
    pos, rad, box, a = p.positions, p.radii, p.box, p.exponent
    n = len(pos)
    i, j, r, s = ref_contact_arrays(pos, rad, box)
    e = np.sum((1 - r / s) ** a / a) / n
    f = (1 - r / s) ** (a - 1) / s
    d = pos[j] - pos[i]
    d -= box * np.round(d / box)
    fv = (f / r)[:, None] * d
    net = np.zeros((n, 2))
    np.add.at(net, i, -fv)
    np.add.at(net, j, fv)
    keep = ref_nonrattlers(n, i, j, d)
    m = keep[i] & keep[j]
    resid = np.max(np.hypot(net[keep, 0], net[keep, 1])) / np.mean(f[m])
    return e, resid, int(keep.sum()), int(m.sum())


def ref_energy_and_residual(p):
    e, resid, _, _ = ref_packing_measures(p)
    return e, resid


def ref_packing_measures_kdtree(p):
    """Independent (E_G, force residual, N_G, contacts among non-rattlers, mean relative
    overlap of those contacts) of a packing, with scipy's periodic k-d tree."""
    pos, rad, box, a = np.asarray(p.positions), np.asarray(p.radii), np.asarray(p.box), p.exponent
    n = len(pos)
    tree = cKDTree(pos, boxsize=box)
    pairs = tree.query_pairs(2 * rad.max(), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d = pos[j] - pos[i]
    d -= box * np.round(d / box)
    r = np.hypot(d[:, 0], d[:, 1])
    s = rad[i] + rad[j]
    keep_pair = r < s
    i, j, d, r, s = i[keep_pair], j[keep_pair], d[keep_pair], r[keep_pair], s[keep_pair]
    x = 1 - r / s
    e = np.sum(x ** a / a) / n
    f = x ** (a - 1) / s
    fv = (f / r)[:, None] * d
    net = np.zeros((n, 2))
    np.add.at(net, i, -fv)
    np.add.at(net, j, fv)
    alive = ref_nonrattlers(n, i, j, d)
    m = alive[i] & alive[j]
    resid = np.max(np.hypot(net[alive, 0], net[alive, 1])) / np.mean(f[m])
    return e, resid, int(alive.sum()), int(m.sum()), float(np.mean(x[m]))


def shoelace_area(points):
    x = np.array([p[0] for p in points])
    y = np.array([p[1] for p in points])
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def ref_network(pos, rad, box, remove_rattlers=True, exponent=2.0):
    """Everything about the contact network, the slow and obvious way."""
    n = len(rad)
    nbrs = {g: {} for g in range(n)}
    energy = 0.0
    virial = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            r = math.hypot(d[0], d[1])
            s = rad[i] + rad[j]
            if r < s:
                nbrs[i][j] = d
                nbrs[j][i] = -d
                energy += (1 - r / s) ** exponent / exponent
                virial += r * (1 - r / s) ** (exponent - 1) / s
    bonds = sorted((i, j) for i in range(n) for j in nbrs[i] if i < j)
    alive = set(range(n))
    if remove_rattlers:
        changed = True
        while changed:
            changed = False
            for g in sorted(alive):
                ang = [math.atan2(d[1], d[0]) for h, d in nbrs[g].items() if h in alive]
                if len(ang) < 3 or in_closed_half_plane(ang):
                    alive.remove(g)
                    changed = True
    rot = {}
    for g in alive:
        rot[g] = sorted((math.atan2(d[1], d[0]), h) for h, d in nbrs[g].items() if h in alive)
    # grains: polygon of contact points, relative angles, edge triangles
    theta, alpha_e, a_g = [], [], {}
    contact_len = []
    for g in alive:
        ring = [nbrs[g][h] * rad[g] / (rad[g] + rad[h]) for _, h in rot[g]]
        a_g[g] = shoelace_area(ring) if len(ring) >= 3 else 0.0
        angles = [a for a, _ in rot[g]]
        k = len(angles)
        for t in range(k):
            nxt = angles[(t + 1) % k] + (2 * math.pi if t + 1 == k else 0.0)
            theta.append(nxt - angles[t])
            u, v = ring[t], ring[(t + 1) % k]
            alpha_e.append(0.5 * (u[0] * v[1] - u[1] * v[0]) / rad[g] ** 2)
            contact_len.append(math.hypot(*ring[t]) / rad[g])
    # faces: next(u -> v) = the half-edge clockwise of v -> u around v
    seen = set()
    faces = []
    for g in sorted(alive):
        for _, h in rot[g]:
            if (g, h) in seen:
                continue
            face = []
            u, v = g, h
            while (u, v) not in seen:
                seen.add((u, v))
                face.append((u, v))
                ring = [w for _, w in rot[v]]
                k = ring.index(u)
                u, v = v, ring[(k - 1) % len(ring)]
            faces.append(face)
    voids = []
    for face in faces:
        p = np.zeros(2)
        centres, contacts = [], []
        for u, v in face:
            d = nbrs[u][v]
            centres.append(p.copy())
            contacts.append(p + d * rad[u] / (rad[u] + rad[v]))
            p = p + d
        voids.append(dict(grains=[u for u, _ in face], centres=np.array(centres),
                          area=shoelace_area(contacts), winding=p, z=len(face)))
    return dict(n=n, bonds=bonds, alive=alive, N_G=len(alive),
                N_C=sum(len(rot[g]) for g in alive), z_g={g: len(rot[g]) for g in alive},
                theta=np.array(theta), alpha_e=np.array(alpha_e), contact_len=np.array(contact_len),
                A_G=sum(a_g.values()), voids=voids, energy=energy, virial=virial)


def ref_fictitious(ref, rad):
    """Fictitious contacts of every void from scipy's Delaunay of its centre cycle."""
    lengths = []
    for v in ref["voids"]:
        k = v["z"]
        if k < 4:
            continue
        P = v["centres"]
        sides = {frozenset((t, (t + 1) % k)) for t in range(k)}
        edges = set()
        for simplex in Delaunay(P).simplices:
            for a in range(3):
                edges.add(frozenset((int(simplex[a]), int(simplex[(a + 1) % 3]))))
        for e in edges - sides:
            i, j = sorted(e)
            gi, gj = v["grains"][i], v["grains"][j]
            lengths.append(np.linalg.norm(P[j] - P[i]) / (rad[gi] + rad[gj]))
    return np.sort(lengths)


def ref_psi6_per_grain(pos, rad, box):
    """|psi_6| per grain over its contacts among non-rattlers, the slow way."""
    n = len(rad)
    nbrs = {g: [] for g in range(n)}
    for i in range(n):
        for j in range(i + 1, n):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            if math.hypot(*d) < rad[i] + rad[j]:
                nbrs[i].append((j, d))
                nbrs[j].append((i, -d))
    alive = set(range(n))
    while True:
        drop = {g for g in alive if sum(1 for h, _ in nbrs[g] if h in alive) < 3}
        if not drop:
            break
        alive -= drop
    out = {}
    for g in alive:
        ds = [d for h, d in nbrs[g] if h in alive]
        out[g] = abs(sum(complex(math.cos(6 * math.atan2(d[1], d[0])),
                                 math.sin(6 * math.atan2(d[1], d[0]))) for d in ds)) / len(ds)
    return out


def ref_radial_counts(points, scales, edges, box, same):
    """Brute-force ordered-pair counts of |p_j - p_i| / scale_i, i != j."""
    counts = np.zeros(len(edges) - 1, dtype=np.int64)
    for i in range(len(points)):
        d = points - points[i]
        d -= box * np.round(d / box)
        r = np.hypot(d[:, 0], d[:, 1])
        mask = np.array([not same(i, j) for j in range(len(points))])
        for s in scales[i]:
            counts += np.histogram(r[mask] / s, edges)[0]
    return counts


def ref_radial_counts_by_class(points, cls1, cls2, scales, box, edges):
    """Ordered-pair counts: every centre of point i counts |p_j - p_i| / its scale."""
    counts = np.zeros(len(edges) - 1, dtype=np.int64)
    for i in range(len(points)):
        d = np.delete(points, i, axis=0) - points[i]
        d -= box * np.round(d / box)
        r = np.hypot(d[:, 0], d[:, 1])
        for c in (cls1[i], cls2[i]):
            if c >= 0:
                counts += np.histogram(r / scales[c], edges)[0]
    return counts


def ref_hessian_dense(positions, radii, box, alpha):
    """Dense Hessian by the textbook formula, pair by pair (all pairs, minimum image)."""
    n = len(radii)
    h = np.zeros((2 * n, 2 * n))
    for i in range(n):
        for j in range(i + 1, n):
            d = positions[j] - positions[i]
            d -= box * np.round(d / box)
            r = np.hypot(*d)
            s = radii[i] + radii[j]
            x = 1.0 - r / s
            if x <= 0:
                continue
            v1 = -x ** (alpha - 1) / s  # V'
            v2 = (alpha - 1) * x ** (alpha - 2) / s**2  # V''
            nn = np.outer(d / r, d / r)
            k = v2 * nn + v1 / r * (np.eye(2) - nn)
            for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
                h[2 * a:2 * a + 2, 2 * b:2 * b + 2] += sign * k
    return h


def ref_hessian_finite_differences(pos, rad, box, alpha, keep, h):
    """Central finite differences of the forces, restricted to the disks in ``keep``."""
    idx = np.flatnonzero(keep)
    m = 2 * len(idx)
    hess = np.empty((m, m))
    for a, i in enumerate(idx):
        for k in range(2):
            p, q = pos.copy(), pos.copy()
            p[i, k] += h
            q[i, k] -= h
            df = (forces(q, rad, box, alpha) - forces(p, rad, box, alpha)) / (2 * h)
            hess[:, 2 * a + k] = df[idx].ravel()
    return 0.5 * (hess + hess.T)


def ref_response(pos, rad, box, alpha):
    """Dense Hessian H, mixed derivatives Xi, affine term A and stress derivative of the
    non-rattlers, pair by pair: the derivatives of ``V(|F d + u_j - u_i|)`` by the chain
    rule on the distance, ``dr/de_a = n . g_a``, ``d2r/de_a de_b = (g_a . g_b - (n . g_a)
    (n . g_b)) / r``, ``g_a = dF/de_a d``."""
    pos, rad, box = (np.asarray(x, float) for x in (pos, rad, box))
    alive, pairs = ref_kept_contacts(pos, rad, box)
    idx = -np.ones(len(rad), int)
    idx[alive] = np.arange(alive.sum())
    m = int(alive.sum())
    H = np.zeros((2 * m, 2 * m))
    Xi = np.zeros((2 * m, 3))
    A = np.zeros((3, 3))
    dU = np.zeros(3)
    for i, j, d in pairs:
        a, b = idx[i], idx[j]
        r = np.hypot(*d)
        s = rad[i] + rad[j]
        x = 1.0 - r / s
        v1 = -x ** (alpha - 1) / s                    # V'
        v2 = (alpha - 1) * x ** (alpha - 2) / s**2    # V''
        n = d / r
        g = [np.array([d[0], 0.0]), np.array([0.0, d[1]]), np.array([d[1], d[0]]) / 2]
        dr = [n @ gg for gg in g]
        for p in range(3):
            dU[p] += v1 * dr[p]
            for q in range(3):
                A[p, q] += v2 * dr[p] * dr[q] + v1 * (g[p] @ g[q] - dr[p] * dr[q]) / r
            # d/de_p of dV/dr_j = V' n
            dg = v2 * dr[p] * n + v1 * (g[p] - n * dr[p]) / r
            Xi[2 * b:2 * b + 2, p] += dg
            Xi[2 * a:2 * a + 2, p] -= dg
        nn = np.outer(n, n)
        k = v2 * nn + v1 / r * (np.eye(2) - nn)
        for u, w, sign in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
            H[2 * u:2 * u + 2, 2 * w:2 * w + 2] += sign * k
    return H, Xi, A, dU, alive


def ref_moduli(pos, rad, box, alpha):
    """``C = (A - Xi^T H^+ Xi) / (Lx Ly)`` with numpy's pseudo-inverse (translations dropped
    by their eigenvalues), Voigt (3, 3); the affine part; the stress; the spectrum."""
    H, Xi, A, dU, _ = ref_response(pos, rad, box, alpha)
    area = float(np.prod(box))
    w, v = np.linalg.eigh(H)
    nz = np.argsort(np.abs(w))[2:]
    Hp = (v[:, nz] / w[nz]) @ v[:, nz].T
    return (A - Xi.T @ Hp @ Xi) / area, A / area, dU / area, w
