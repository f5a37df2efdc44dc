"""Slow, obviously correct reference implementations shared by several test modules."""

import math

import numpy as np

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
