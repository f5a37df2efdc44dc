"""Sparse Cholesky factorisation of the block matrices of a packing (numba).

The matrices are symmetric, with one node per disk and 2 x 2 blocks: a diagonal block per node
and an off-diagonal block per pair of a *pattern* (the disk pairs that may interact; blocks of
pairs that do not touch are explicit zeros, so one pattern serves while contacts come and go).
Both kinds of block are symmetric, given as ``(xx, xy, yy)``. This is the structure of the
Hessian of a contact network (``kernels.hessian``), which the Newton endgame of the O'Hern
search (``kernels.newton``) and the linear-response observables factor.

Three steps, each a jitted core:

* **Ordering** (``_nd_order``): geometric nested dissection. The disks' own positions split the
  box in halves along its longer side, recursively; the separator of a split is the smaller of
  the two sets of nodes with a neighbour on the other side, numbered after both halves. On the
  torus the first cut's separator holds both the middle line and the periodic boundary, as it
  must. Halves of at most ``LEAF`` nodes are left in any order.
* **Symbolic analysis** (``_symbolic_core``): elimination tree, postorder, the column structures of
  the factor at node level, fundamental supernodes (consecutive nodes with nested structures),
  the fronts' row lists, where each child's update matrix lands in its parent's front and where
  each given block lands in a front. It depends on the pattern only, so it is done once per
  pattern and reused for every numerical factorisation on it.
* **Numerical factorisation** (``_numeric_core``): multifrontal. Supernodes are visited children
  first; each front (a dense matrix over the supernode's columns and its update rows) gathers
  the given blocks and its children's update matrices, factors its pivot columns, and leaves
  its Schur complement on a stack for its parent. Dense kernels are plain loops over
  contiguous columns, in a fixed order: the factor is a pure function of the inputs (the same
  bits on any machine of the same architecture, whatever the thread count). A pivot at or
  below ``PIVOT_REL`` times its diagonal entry of the input stops the factorisation: the
  matrix is not (numerically) positive definite, and the failing column is returned.
* **Solve** (``_solve_core``): forward and backward substitution through the supernodes.

Checked wrappers: ``analyse`` (ordering + symbolic), ``factor``, ``solve`` and ``to_dense``
for tests and for users who bring their own blocks.
"""

from collections import namedtuple

import numpy as np
from numba import njit

LEAF = 8  # halves of at most this many nodes are not split further
CUTS = 9  # candidate cut positions per split (default of ``analyse``; the Newton endgame's)
CUTS_ABOVE = 256  # ... in halves of more than this many nodes (else the middle)
CUT_SPREAD = 0.3  # ... spread over this fraction of the region's side around its middle
PIVOT_REL = 1e-13
# relaxed amalgamation (nodes, explicit-zero fractions), after CHOLMOD's defaults
RELAX = (2, 8, 24)
ZRELAX = (0.8, 0.1, 0.05)  # a pivot at or below this fraction of its input diagonal entry fails

Symbolic = namedtuple("Symbolic", [
    "n",  # nodes (2 n unknowns)
    "perm",  # (n,) new -> old node
    "iperm",  # (n,) old -> new node
    "sup_first",  # (nsup + 1,) first new node of each supernode (contiguous ranges)
    "sup_parent",  # (nsup,) parent supernode, -1 for a root
    "sup_nchild",  # (nsup,) children of each supernode
    "upd_ptr",  # (nsup + 1,) update rows of supernode s: upd_rows[upd_ptr[s]:upd_ptr[s + 1]]
    "upd_rows",  # new node numbers, ascending
    "rel",  # aligned with upd_rows: position of each update row in the parent's front (nodes)
    "l_ptr",  # (nsup + 1,) offset of supernode s's panel (m x w, column major) in the factor
    "pair_ptr",  # (nsup + 1,) blocks of pairs landing in supernode s: pair_idx[pair_ptr[s]:...]
    "pair_idx",  # indices into the given pair list
    "pair_col",  # aligned with pair_idx: local column node in the front
    "pair_row",  # aligned with pair_idx: local row node in the front
    "max_front",  # largest front size (unknowns)
    "stack_size",  # largest total size of the update matrices waiting on the stack
])


@njit(cache=True)
def _adjacency(n, pi, pj):
    """Symmetric CSR adjacency ``(start, nbr)`` of the pairs (self pairs and duplicates kept
    out by the caller)."""
    deg = np.zeros(n + 1, dtype=np.int64)
    for k in range(pi.shape[0]):
        deg[pi[k] + 1] += 1
        deg[pj[k] + 1] += 1
    for i in range(n):
        deg[i + 1] += deg[i]
    fill = deg[:-1].copy()
    nbr = np.empty(deg[n], dtype=np.int64)
    for k in range(pi.shape[0]):
        a = pi[k]
        b = pj[k]
        nbr[fill[a]] = b
        fill[a] += 1
        nbr[fill[b]] = a
        fill[b] += 1
    return deg, nbr


@njit(cache=True)
def _min_cover(nodes, na, nb, start, nbr, tag, ta, tb, cover, match, seen, queue, prev):
    """Mark in ``cover`` a minimum vertex cover of the edges between A = ``nodes[:na]``
    (tagged ``ta``) and B = ``nodes[na:na + nb]`` (tagged ``tb``): a maximum matching by
    breadth-first augmenting paths, then Konig's construction. Every edge between A and B
    then has an end in the cover, so the cover separates them."""
    for k in range(na + nb):
        v = nodes[k]
        match[v] = -1
        cover[v] = False
        seen[v] = 0
    stamp = 0
    for k in range(na):
        a = nodes[k]
        stamp += 1
        qh = 0
        qt = 1
        queue[0] = a
        seen[a] = stamp
        found = -1
        while qh < qt and found == -1:
            x = queue[qh]
            qh += 1
            for e in range(start[x], start[x + 1]):
                b = nbr[e]
                if tag[b] != tb or seen[b] == stamp:
                    continue
                seen[b] = stamp
                prev[b] = x
                if match[b] == -1:
                    found = b
                    break
                y = match[b]
                if seen[y] != stamp:
                    seen[y] = stamp
                    queue[qt] = y
                    qt += 1
        b = found
        while b != -1:
            x = prev[b]
            old = match[x]
            match[x] = b
            match[b] = x
            b = old
    # Konig: Z = reachable from free A vertices by alternating paths
    stamp += 1
    qt = 0
    for k in range(na):
        a = nodes[k]
        if match[a] == -1:
            seen[a] = stamp
            queue[qt] = a
            qt += 1
    qh = 0
    while qh < qt:
        x = queue[qh]
        qh += 1
        for e in range(start[x], start[x + 1]):
            b = nbr[e]
            if tag[b] != tb or seen[b] == stamp:
                continue
            seen[b] = stamp
            y = match[b]
            if y != -1 and seen[y] != stamp:
                seen[y] = stamp
                queue[qt] = y
                qt += 1
    for k in range(na):
        a = nodes[k]
        if match[a] != -1 and seen[a] != stamp:
            cover[a] = True
    for k in range(na, na + nb):
        b = nodes[k]
        if seen[b] == stamp:
            cover[b] = True


@njit(cache=True)
def _split(buf, lo, hi, positions, dim, cut, tmp):
    """``tmp[:na]`` the nodes of ``buf[lo:hi]`` below ``cut`` along ``dim``, then the
    ``nb`` others, both in their order in ``buf``; returns ``(na, nb)``."""
    na = 0
    for k in range(lo, hi):
        if positions[buf[k], dim] < cut:
            tmp[na] = buf[k]
            na += 1
    nb = 0
    for k in range(lo, hi):
        if positions[buf[k], dim] >= cut:
            tmp[na + nb] = buf[k]
            nb += 1
    return na, nb


@njit(cache=True)
def _nd_order(positions, box, start, nbr, cuts_max):
    """Nested-dissection order (new -> old) of the nodes of the graph ``(start, nbr)`` from
    the positions (wrapped into the box). See the module docstring. ``cuts_max``: candidate
    cuts per split of more than ``CUTS_ABOVE`` nodes (1: the middle only, a faster ordering
    with more fill)."""
    n = positions.shape[0]
    order = np.empty(n, dtype=np.int64)
    buf = np.arange(n)
    tmp = np.empty(n, dtype=np.int64)
    tag = np.zeros(n, dtype=np.int64)
    cover = np.zeros(n, dtype=np.bool_)
    match = np.full(n, -1, dtype=np.int64)
    seen = np.zeros(n, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    prev = np.empty(n, dtype=np.int64)
    # task stack: (lo, hi, out_lo) into buf / order, and the region [x0, x1) x [y0, y1)
    cap = 64
    t_int = np.empty((cap, 3), dtype=np.int64)
    t_reg = np.empty((cap, 4))
    t_int[0, 0] = 0
    t_int[0, 1] = n
    t_int[0, 2] = 0
    t_reg[0, 0] = 0.0
    t_reg[0, 1] = box[0]
    t_reg[0, 2] = 0.0
    t_reg[0, 3] = box[1]
    top = 1
    counter = 0
    min_side = 1e-12 * max(box[0], box[1])
    while top > 0:
        top -= 1
        lo = t_int[top, 0]
        hi = t_int[top, 1]
        out = t_int[top, 2]
        x0 = t_reg[top, 0]
        x1 = t_reg[top, 1]
        y0 = t_reg[top, 2]
        y1 = t_reg[top, 3]
        size = hi - lo
        if size <= LEAF or max(x1 - x0, y1 - y0) < min_side:
            for k in range(size):
                order[out + k] = buf[lo + k]
            continue
        if top + 2 > cap:
            cap *= 2
            t_int2 = np.empty((cap, 3), dtype=np.int64)
            t_reg2 = np.empty((cap, 4))
            t_int2[:top] = t_int[:top]
            t_reg2[:top] = t_reg[:top]
            t_int = t_int2
            t_reg = t_reg2
        dim = 0 if (x1 - x0) >= (y1 - y0) else 1
        c0 = x0 if dim == 0 else y0
        c1 = x1 if dim == 0 else y1
        # the cut among CUTS positions around the middle with the smallest separator
        best = -1
        best_score = 0.0
        best_cut = 0.5 * (c0 + c1)
        cuts = cuts_max if size > CUTS_ABOVE else 1
        for q in range(cuts):
            cut = c0 + (c1 - c0) * (0.5 + CUT_SPREAD * (q - (cuts - 1) / 2) / max(cuts - 1, 1))
            na, nb = _split(buf, lo, hi, positions, dim, cut, tmp)
            if na == 0 or nb == 0:
                continue
            counter += 2
            for k in range(na):
                tag[tmp[k]] = counter
            for k in range(na, na + nb):
                tag[tmp[k]] = counter + 1
            _min_cover(tmp, na, nb, start, nbr, tag, counter, counter + 1, cover, match, seen,
                       queue, prev)
            ca = 0
            cb = 0
            for k in range(na):
                if cover[tmp[k]]:
                    ca += 1
            for k in range(na, na + nb):
                if cover[tmp[k]]:
                    cb += 1
            # ratio cut: separator size against the balance of the two sides
            score = (ca + cb) / (max(na - ca, 1) * max(nb - cb, 1))
            if best < 0 or score < best_score:
                best = 1
                best_score = score
                best_cut = cut
        na, nb = _split(buf, lo, hi, positions, dim, best_cut, tmp)
        if na == 0 or nb == 0:
            # every node in one half: the same nodes in that half of the region
            t_int[top, 0] = lo
            t_int[top, 1] = hi
            t_int[top, 2] = out
            if dim == 0:
                if na == 0:
                    x0 = best_cut
                else:
                    x1 = best_cut
            else:
                if na == 0:
                    y0 = best_cut
                else:
                    y1 = best_cut
            t_reg[top, 0] = x0
            t_reg[top, 1] = x1
            t_reg[top, 2] = y0
            t_reg[top, 3] = y1
            top += 1
            continue
        counter += 2
        for k in range(na):
            tag[tmp[k]] = counter
        for k in range(na, na + nb):
            tag[tmp[k]] = counter + 1
        # the separator: a minimum vertex cover of the edges between A and B
        _min_cover(tmp, na, nb, start, nbr, tag, counter, counter + 1, cover, match, seen,
                   queue, prev)
        # rewrite buf[lo:hi] as: A part, B part, separator
        pa = lo
        for k in range(na):
            if not cover[tmp[k]]:
                buf[pa] = tmp[k]
                pa += 1
        pb = pa
        for k in range(na, na + nb):
            if not cover[tmp[k]]:
                buf[pb] = tmp[k]
                pb += 1
        ps = pb
        for k in range(na + nb):
            if cover[tmp[k]]:
                buf[ps] = tmp[k]
                ps += 1
        ns = hi - pb
        for k in range(ns):
            order[out + size - ns + k] = buf[pb + k]
        # the two halves (A first in the final order)
        for half in range(2):
            if half == 0:
                t_int[top, 0] = lo
                t_int[top, 1] = pa
                t_int[top, 2] = out
            else:
                t_int[top, 0] = pa
                t_int[top, 1] = pb
                t_int[top, 2] = out + (pa - lo)
            if dim == 0:
                t_reg[top, 0] = x0 if half == 0 else best_cut
                t_reg[top, 1] = best_cut if half == 0 else x1
                t_reg[top, 2] = y0
                t_reg[top, 3] = y1
            else:
                t_reg[top, 0] = x0
                t_reg[top, 1] = x1
                t_reg[top, 2] = y0 if half == 0 else best_cut
                t_reg[top, 3] = best_cut if half == 0 else y1
            top += 1
    return order


@njit(cache=True)
def _etree(n, start, nbr):
    """Elimination tree of the graph in its own numbering (Liu's algorithm with path
    compression); -1 marks a root."""
    parent = np.full(n, -1, dtype=np.int64)
    anc = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        for e in range(start[k], start[k + 1]):
            i = nbr[e]
            while i != -1 and i < k:
                nxt = anc[i]
                anc[i] = k
                if nxt == -1:
                    parent[i] = k
                i = nxt
    return parent


@njit(cache=True)
def _children(parent):
    """Children of each node of a forest (``parent``, -1 for roots) as compressed lists:
    those of ``v`` are ``child[start[v]:start[v + 1]]``, in increasing order."""
    n = parent.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    for v in range(n):
        if parent[v] != -1:
            start[parent[v] + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    child = np.empty(start[n], dtype=np.int64)
    for v in range(n):
        p = parent[v]
        if p != -1:
            child[fill[p]] = v
            fill[p] += 1
    return start, child


@njit(cache=True)
def _postorder(n, parent):
    """Nodes in a postorder of the forest (children in increasing order before parents)."""
    head = np.full(n, -1, dtype=np.int64)
    nxt = np.full(n, -1, dtype=np.int64)
    for v in range(n - 1, -1, -1):
        p = parent[v]
        if p != -1:
            nxt[v] = head[p]
            head[p] = v
    post = np.empty(n, dtype=np.int64)
    stack = np.empty(n, dtype=np.int64)
    k = 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top = 0
        stack[0] = root
        while top >= 0:
            v = stack[top]
            c = head[v]
            if c == -1:
                top -= 1
                post[k] = v
                k += 1
            else:
                head[v] = nxt[c]
                top += 1
                stack[top] = c
    return post


@njit(cache=True)
def _relabel(n, pi, pj, perm):
    """Adjacency of the pairs in the numbering ``iperm = perm^-1`` (old -> new)."""
    iperm = np.empty(n, dtype=np.int64)
    for a in range(n):
        iperm[perm[a]] = a
    qi = np.empty(pi.shape[0], dtype=np.int64)
    qj = np.empty(pi.shape[0], dtype=np.int64)
    for k in range(pi.shape[0]):
        qi[k] = iperm[pi[k]]
        qj[k] = iperm[pj[k]]
    start, nbr = _adjacency(n, qi, qj)
    return iperm, qi, qj, start, nbr


@njit(cache=True)
def _symbolic_core(n, pi, pj, order):
    """Symbolic analysis for the pairs ``(pi, pj)`` (old numbering, ``pi != pj``, no
    duplicates) under the fill-reducing ``order`` (new -> old). Returns the fields of
    ``Symbolic`` after ``n`` (see its definition)."""
    # postorder the elimination tree and fold it into the ordering
    iperm, qi, qj, start, nbr = _relabel(n, pi, pj, order)
    parent0 = _etree(n, start, nbr)
    post = _postorder(n, parent0)
    perm = order[post]
    iperm, qi, qj, start, nbr = _relabel(n, pi, pj, perm)
    parent = _etree(n, start, nbr)
    cstart, child = _children(parent)
    # column structures (rows below the diagonal, node level), children first
    sptr = np.zeros(n + 1, dtype=np.int64)
    cap = 8 * n + 16
    srows = np.empty(cap, dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    work = np.empty(n, dtype=np.int64)
    for k in range(n):
        cnt = 0
        mark[k] = k
        for e in range(start[k], start[k + 1]):
            i = nbr[e]
            if i > k and mark[i] != k:
                mark[i] = k
                work[cnt] = i
                cnt += 1
        for e in range(cstart[k], cstart[k + 1]):
            c = child[e]
            for q in range(sptr[c], sptr[c + 1]):
                i = srows[q]
                if mark[i] != k:
                    mark[i] = k
                    work[cnt] = i
                    cnt += 1
        if sptr[k] + cnt > cap:
            cap = max(2 * cap, sptr[k] + cnt)
            s2 = np.empty(cap, dtype=np.int64)
            s2[:sptr[k]] = srows[:sptr[k]]
            srows = s2
        srt = np.sort(work[:cnt])
        srows[sptr[k]:sptr[k] + cnt] = srt
        sptr[k + 1] = sptr[k] + cnt
    # fundamental supernodes
    first = np.empty(n + 1, dtype=np.int64)
    nsup = 0
    for k in range(n):
        cc_k = sptr[k + 1] - sptr[k]
        join = False
        if k > 0 and parent[k - 1] == k and cstart[k + 1] - cstart[k] == 1:
            if sptr[k] - sptr[k - 1] == cc_k + 1:
                join = True
        if not join:
            first[nsup] = k
            nsup += 1
    first[nsup] = n
    # relaxed amalgamation: a supernode merges into its parent when the parent follows it
    # directly (its last child) and the merged front stays small or holds few explicit zeros
    keep = np.ones(nsup, dtype=np.bool_)
    true_nz = np.zeros(nsup, dtype=np.int64)
    for s in range(nsup):
        for k in range(first[s], first[s + 1]):
            true_nz[s] += sptr[k + 1] - sptr[k] + 1
    for s in range(nsup - 1):
        last = first[s + 1] - 1
        if parent[last] != first[s + 1]:
            continue
        ns = first[s + 2] - first[s]
        nu = sptr[first[s + 2]] - sptr[first[s + 2] - 1]
        stored = ns * (ns + 1) // 2 + ns * nu
        merged_true = true_nz[s] + true_nz[s + 1]
        zeros = 1.0 - merged_true / stored
        if ns <= RELAX[0] or (ns <= RELAX[1] and zeros < ZRELAX[0]) or (
                ns <= RELAX[2] and zeros < ZRELAX[1]) or zeros < ZRELAX[2]:
            keep[s] = False
            first[s + 1] = first[s]
            true_nz[s + 1] = merged_true
    m = 0
    for s in range(nsup):
        if keep[s]:
            first[m] = first[s]
            m += 1
    first[m] = n
    nsup = m
    sup_first = first[:nsup + 1].copy()
    node_sup = np.empty(n, dtype=np.int64)
    for s in range(nsup):
        for k in range(sup_first[s], sup_first[s + 1]):
            node_sup[k] = s
    # update rows of each supernode: the structure of its last node
    upd_ptr = np.zeros(nsup + 1, dtype=np.int64)
    for s in range(nsup):
        last = sup_first[s + 1] - 1
        upd_ptr[s + 1] = upd_ptr[s] + (sptr[last + 1] - sptr[last])
    upd_rows = np.empty(upd_ptr[nsup], dtype=np.int64)
    sup_parent = np.full(nsup, -1, dtype=np.int64)
    sup_nchild = np.zeros(nsup, dtype=np.int64)
    for s in range(nsup):
        last = sup_first[s + 1] - 1
        upd_rows[upd_ptr[s]:upd_ptr[s + 1]] = srows[sptr[last]:sptr[last + 1]]
        if parent[last] != -1:
            p = node_sup[parent[last]]
            sup_parent[s] = p
            sup_nchild[p] += 1
    # positions of each child's update rows in its parent's front (node level)
    rel = np.empty(upd_ptr[nsup], dtype=np.int64)
    pos = np.full(n, -1, dtype=np.int64)
    # children of p come before p: fill pos for p lazily, per parent
    ch_start, ch = _children(sup_parent)
    for p in range(nsup):
        f = sup_first[p]
        ns = sup_first[p + 1] - f
        for a in range(ns):
            pos[f + a] = a
        for q in range(upd_ptr[p], upd_ptr[p + 1]):
            pos[upd_rows[q]] = ns + (q - upd_ptr[p])
        for e in range(ch_start[p], ch_start[p + 1]):
            c = ch[e]
            for q in range(upd_ptr[c], upd_ptr[c + 1]):
                rel[q] = pos[upd_rows[q]]
    # panels and stack
    l_ptr = np.zeros(nsup + 1, dtype=np.int64)
    max_front = 0
    stack = 0
    stack_size = 0
    stk = np.empty(nsup + 1, dtype=np.int64)  # sizes of the update matrices on the stack
    top = 0
    for s in range(nsup):
        w = 2 * (sup_first[s + 1] - sup_first[s])
        u = 2 * (upd_ptr[s + 1] - upd_ptr[s])
        m = w + u
        l_ptr[s + 1] = l_ptr[s] + m * w
        if m > max_front:
            max_front = m
        for c in range(sup_nchild[s]):
            top -= 1
            stack -= stk[top]
        stk[top] = u * u
        top += 1
        stack += u * u
        if stack > stack_size:
            stack_size = stack
    # where each pair's block lands: the supernode of its lower-numbered node
    npair = pi.shape[0]
    pair_ptr = np.zeros(nsup + 1, dtype=np.int64)
    psup = np.empty(npair, dtype=np.int64)
    for k in range(npair):
        a = min(qi[k], qj[k])
        psup[k] = node_sup[a]
        pair_ptr[psup[k] + 1] += 1
    for s in range(nsup):
        pair_ptr[s + 1] += pair_ptr[s]
    pfill = pair_ptr[:-1].copy()
    pair_idx = np.empty(npair, dtype=np.int64)
    pair_col = np.empty(npair, dtype=np.int64)
    pair_row = np.empty(npair, dtype=np.int64)
    for k in range(npair):
        s = psup[k]
        a = min(qi[k], qj[k])
        b = max(qi[k], qj[k])
        f = sup_first[s]
        ns = sup_first[s + 1] - f
        q = pfill[s]
        pfill[s] += 1
        pair_idx[q] = k
        pair_col[q] = a - f
        if b < sup_first[s + 1]:
            pair_row[q] = b - f
        else:
            lo = upd_ptr[s]
            hi = upd_ptr[s + 1]
            j = lo + np.searchsorted(upd_rows[lo:hi], b)
            pair_row[q] = ns + (j - lo)
    return (perm, iperm, sup_first, sup_parent, sup_nchild, upd_ptr, upd_rows, rel, l_ptr,
            pair_ptr, pair_idx, pair_col, pair_row, max_front, stack_size)


@njit(cache=True)
def _numeric_core(perm, sup_first, sup_nchild, upd_ptr, upd_rows, rel, l_ptr, pair_ptr,
                  pair_idx, pair_col, pair_row, max_front, stack_size, diag, offdiag, lval):
    """Multifrontal Cholesky factor of the matrix with diagonal blocks ``diag`` (n, 3) (old
    node numbering) and off-diagonal blocks ``offdiag`` (npair, 3) of the analysed pairs,
    written into ``lval`` (``l_ptr[-1]`` values: supernode ``s``'s panel of ``m`` rows and
    ``w`` columns, column after column). Returns -1 on success, else the first unknown (new
    numbering) whose pivot failed (see ``PIVOT_REL``)."""
    nsup = sup_first.shape[0] - 1
    front = np.empty((max_front, max_front))  # front[column, row], lower triangle used
    stack = np.empty(max(stack_size, 1))
    stk_off = np.empty(nsup + 1, dtype=np.int64)
    stk_sup = np.empty(nsup + 1, dtype=np.int64)
    dof = np.empty(max_front, dtype=np.int64)
    top = 0
    sp = 0
    adiag = np.empty(max_front)
    for s in range(nsup):
        f = sup_first[s]
        ns = sup_first[s + 1] - f
        w = 2 * ns
        nu = upd_ptr[s + 1] - upd_ptr[s]
        m = w + 2 * nu
        for c in range(m):
            for r in range(c, m):
                front[c, r] = 0.0
        for a in range(ns):
            v = perm[f + a]
            c0 = 2 * a
            front[c0, c0] += diag[v, 0]
            front[c0, c0 + 1] += diag[v, 1]
            front[c0 + 1, c0 + 1] += diag[v, 2]
        for q in range(pair_ptr[s], pair_ptr[s + 1]):
            k = pair_idx[q]
            c0 = 2 * pair_col[q]
            r0 = 2 * pair_row[q]
            front[c0, r0] += offdiag[k, 0]
            front[c0, r0 + 1] += offdiag[k, 1]
            front[c0 + 1, r0] += offdiag[k, 1]
            front[c0 + 1, r0 + 1] += offdiag[k, 2]
        for c in range(w):
            adiag[c] = front[c, c]
        # extend-add the children's update matrices, the latest ones on the stack
        for e in range(sup_nchild[s]):
            top -= 1
            off = stk_off[top]
            cs = stk_sup[top]
            lo = upd_ptr[cs]
            u = 2 * (upd_ptr[cs + 1] - lo)
            for q in range(upd_ptr[cs + 1] - lo):
                dof[2 * q] = 2 * rel[lo + q]
                dof[2 * q + 1] = 2 * rel[lo + q] + 1
            for j in range(u):
                cj = dof[j]
                base = off + j * u
                for i in range(j, u):
                    front[cj, dof[i]] += stack[base + i]
            sp = off
        # dense partial Cholesky: the w pivot columns, then the Schur complement
        for k in range(w):
            d = front[k, k]
            if not d > PIVOT_REL * adiag[k]:
                return 2 * f + k
            lkk = np.sqrt(d)
            front[k, k] = lkk
            inv = 1.0 / lkk
            for i in range(k + 1, m):
                front[k, i] *= inv
            for j in range(k + 1, w):
                c = front[k, j]
                if c != 0.0:
                    for i in range(j, m):
                        front[j, i] -= front[k, i] * c
        w4 = w - w % 4
        for j in range(w, m):
            for k in range(0, w4, 4):
                c0 = front[k, j]
                c1 = front[k + 1, j]
                c2 = front[k + 2, j]
                c3 = front[k + 3, j]
                for i in range(j, m):
                    front[j, i] -= (front[k, i] * c0 + front[k + 1, i] * c1
                                    + front[k + 2, i] * c2 + front[k + 3, i] * c3)
            for k in range(w4, w):
                c = front[k, j]
                for i in range(j, m):
                    front[j, i] -= front[k, i] * c
        base = l_ptr[s]
        for c in range(w):
            for r in range(m):
                lval[base + c * m + r] = front[c, r] if r >= c else 0.0
        u = m - w
        if u > 0:
            stk_off[top] = sp
            stk_sup[top] = s
            top += 1
            for j in range(u):
                for i in range(j, u):
                    stack[sp + j * u + i] = front[w + j, w + i]
            sp += u * u
    return -1


@njit(cache=True)
def _solve_core(perm, sup_first, upd_ptr, upd_rows, l_ptr, lval, b):
    """``x`` with ``L L^T x = P b P^T`` undone: the solution of the factored system for the
    right-hand side ``b`` (2 n,) in the old numbering."""
    n = perm.shape[0]
    nsup = sup_first.shape[0] - 1
    y = np.empty(2 * n)
    for a in range(n):
        y[2 * a] = b[2 * perm[a]]
        y[2 * a + 1] = b[2 * perm[a] + 1]
    # forward: L y = b
    for s in range(nsup):
        f = sup_first[s]
        w = 2 * (sup_first[s + 1] - f)
        lo = upd_ptr[s]
        m = w + 2 * (upd_ptr[s + 1] - lo)
        base = l_ptr[s]
        for k in range(w):
            col = base + k * m
            yk = y[2 * f + k] / lval[col + k]
            y[2 * f + k] = yk
            if yk != 0.0:
                for i in range(k + 1, w):
                    y[2 * f + i] -= lval[col + i] * yk
                for i in range(w, m):
                    q = i - w
                    y[2 * upd_rows[lo + q // 2] + q % 2] -= lval[col + i] * yk
    # backward: L^T x = y
    for s in range(nsup - 1, -1, -1):
        f = sup_first[s]
        w = 2 * (sup_first[s + 1] - f)
        lo = upd_ptr[s]
        m = w + 2 * (upd_ptr[s + 1] - lo)
        base = l_ptr[s]
        for k in range(w - 1, -1, -1):
            col = base + k * m
            t = y[2 * f + k]
            for i in range(k + 1, w):
                t -= lval[col + i] * y[2 * f + i]
            for i in range(w, m):
                q = i - w
                t -= lval[col + i] * y[2 * upd_rows[lo + q // 2] + q % 2]
            y[2 * f + k] = t / lval[col + k]
    x = np.empty(2 * n)
    for a in range(n):
        x[2 * perm[a]] = y[2 * a]
        x[2 * perm[a] + 1] = y[2 * a + 1]
    return x


# ---- checked wrappers ----------------------------------------------------------------------

class NotPositiveDefinite(ValueError):
    """The matrix is not (numerically) positive definite; ``dof`` is the failing unknown."""

    def __init__(self, dof):
        super().__init__(f"matrix not positive definite: pivot {dof} at or below "
                         f"{PIVOT_REL:g} times its diagonal entry")
        self.dof = dof


def _pairs(n, pairs_i, pairs_j):
    pi = np.ascontiguousarray(pairs_i, dtype=np.int64)
    pj = np.ascontiguousarray(pairs_j, dtype=np.int64)
    if pi.shape != pj.shape or pi.ndim != 1:
        raise ValueError(f"pairs: expected two 1-d arrays of one length, got {pi.shape} and {pj.shape}")
    if pi.size and (pi.min() < 0 or pj.min() < 0 or pi.max() >= n or pj.max() >= n):
        raise ValueError(f"pairs: expected node indices in [0, {n})")
    if np.any(pi == pj):
        raise ValueError("pairs: a node paired with itself")
    key = np.minimum(pi, pj) * n + np.maximum(pi, pj)
    if np.unique(key).size != key.size:
        raise ValueError("pairs: a pair listed twice")
    return pi, pj


def analyse(positions, box, pairs_i, pairs_j, cuts=CUTS):
    """Ordering and symbolic analysis of the block pattern of the pairs ``(pairs_i[k],
    pairs_j[k])`` of the disks at ``positions`` in ``box``. Returns a ``Symbolic``. ``cuts``:
    candidate cut positions per large split (``CUTS``; 1 orders faster, with more fill)."""
    if not (isinstance(cuts, (int, np.integer)) and cuts >= 1):
        raise ValueError(f"cuts: expected an integer >= 1, got {cuts!r}")
    from kernels.space import _as_box, _as_positions, _wrap_core

    b = _as_box(box)
    pos = _wrap_core(_as_positions(positions), b)
    n = pos.shape[0]
    pi, pj = _pairs(n, pairs_i, pairs_j)
    start, nbr = _adjacency(n, pi, pj)
    order = _nd_order(pos, b, start, nbr, int(cuts))
    return Symbolic(n, *_symbolic_core(n, pi, pj, order))


def _blocks(name, arr, rows):
    a = np.ascontiguousarray(arr, dtype=np.float64)
    if a.shape != (rows, 3):
        raise ValueError(f"{name}: expected shape ({rows}, 3) (xx, xy, yy), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values")
    return a


def factor(sym, diag, offdiag):
    """Cholesky factor (flat panel values) of the matrix with diagonal blocks ``diag`` (n, 3)
    and off-diagonal blocks ``offdiag`` (npair, 3) on the pattern analysed in ``sym``.
    Raises ``NotPositiveDefinite``."""
    d = _blocks("diag", diag, sym.n)
    o = _blocks("offdiag", offdiag, sym.pair_idx.shape[0])
    lval = np.empty(sym.l_ptr[-1])
    bad = _numeric_core(sym.perm, sym.sup_first, sym.sup_nchild, sym.upd_ptr, sym.upd_rows,
                        sym.rel, sym.l_ptr, sym.pair_ptr, sym.pair_idx, sym.pair_col,
                        sym.pair_row, sym.max_front, sym.stack_size, d, o, lval)
    if bad >= 0:
        raise NotPositiveDefinite(int(bad))
    return lval


def solve(sym, lval, rhs):
    """Solution ``x`` (2 n,) of ``A x = rhs`` for the matrix factored into ``lval``; the
    unknowns are ordered ``x0, y0, x1, y1, ...`` (old node numbering)."""
    b = np.ascontiguousarray(rhs, dtype=np.float64).ravel()
    if b.shape != (2 * sym.n,):
        raise ValueError(f"rhs: expected {2 * sym.n} values, got {np.shape(rhs)}")
    return _solve_core(sym.perm, sym.sup_first, sym.upd_ptr, sym.upd_rows, sym.l_ptr, lval, b)


def to_dense(n, pairs_i, pairs_j, diag, offdiag):
    """The (2 n, 2 n) dense matrix of the blocks (for tests and small systems)."""
    pi, pj = _pairs(n, pairs_i, pairs_j)
    d = _blocks("diag", diag, n)
    o = _blocks("offdiag", offdiag, pi.shape[0])
    a = np.zeros((2 * n, 2 * n))
    for v in range(n):
        a[2 * v:2 * v + 2, 2 * v:2 * v + 2] += [[d[v, 0], d[v, 1]], [d[v, 1], d[v, 2]]]
    for k in range(pi.shape[0]):
        blk = np.array([[o[k, 0], o[k, 1]], [o[k, 1], o[k, 2]]])
        i, j = pi[k], pj[k]
        a[2 * i:2 * i + 2, 2 * j:2 * j + 2] += blk
        a[2 * j:2 * j + 2, 2 * i:2 * i + 2] += blk
    return a


def fill(sym):
    """``(nnz(L), multiply-adds)`` of the factor's panels (dense panels, zeros included)."""
    w = 2 * np.diff(sym.sup_first)
    m = w + 2 * np.diff(sym.upd_ptr)
    nnz = int(np.sum(w * m - w * (w - 1) // 2))
    flops = float(np.sum([sum((mm - k) ** 2 for k in range(ww)) for ww, mm in zip(w, m)]))
    return nnz, flops


__all__ = ["Symbolic", "NotPositiveDefinite", "analyse", "factor", "solve", "to_dense", "fill",
           "LEAF", "PIVOT_REL"]
