"""Every bootstrap of the reducer, with the random generator each one draws from.

A bootstrap here resamples what is independent in a campaign and recomputes a statistic on every
replica; the error is the spread of the replicas. What is resampled depends on the statistic:

* ``cell_means``: packings within each cell (the scaling fits of packings that are independent);
* ``seed_means`` and ``seed_cell_means``: whole seeds, a seed's packings at every energy together
  (an energy ladder's packings of one seed share a history; ``seed_means`` serves the scaling fits
  of a ladder, ``seed_cell_means`` the jamming point of ``campaign.results.protocols``);
* ``clusters``: whole clusters of pairs (the variants compared packing by packing,
  ``campaign.results.tradeoff``: the (N, seed) chains);
* ``resampled_sums``: the packings of a cell, their histograms summed (the exponents of
  ``campaign.results.response``).

**A replica that draws none of a cell's seeds.** The two seed bootstraps differ here, and each keeps
its own answer: ``seed_means`` gives that cell the mean of all its packings in that replica (the
replica is kept; the cell's spread in it is 0, which makes a sparsely covered cell's error
smaller), ``seed_cell_means`` drops the replica (the error is then the spread of the replicas that
hold every cell). With every seed in every cell, as a fixed grid gives, neither case arises.

**Streams.** Every generator is ``generator(key)``: PCG64 seeded by ``SeedSequence(key)``, the key a
list of integers led by the reducer's ``--seed`` (``Settings.boot_seed``):

* ``[boot_seed, g]``: the scaling fits of the g-th (variant, N_G) in sorted order
  (``campaign.results.scaling``);
* ``[boot_seed, 7]``: the variants against the reference, one stream the variants draw from in turn
  (``campaign.results.tradeoff``);
* ``[boot_seed, 11, v, N_G]``: the jamming point of the v-th variant at N_G, each quantity from the
  stream's start (``campaign.results.protocols``);
* ``[boot_seed, c]``: the response exponents of the c-th cell; ``[boot_seed, 7, N_G]``: those
  pooled at N_G (``campaign.results.response``).

Some streams coincide: the variants' ``[boot_seed, 7]`` is also that of the scaling fits of the
(variant, N_G) of index 7 and of the response exponents of cell 7, and ``[boot_seed, g]`` with
``g = c`` serves both the fits of (variant, N_G) ``g`` and the exponents of cell ``c`` (and
``SeedSequence`` reads a key of fewer than four words as if padded with zeros, so ``[boot_seed, 7]``
is ``[boot_seed, 7, 0]`` too). They resample different data, so each error alone is as it should be,
but two such errors are not independent draws. The keys are kept as they were, so that every error
stays bit for bit the same.
"""

from __future__ import annotations

import numpy as np


def generator(key) -> np.random.Generator:
    """The random generator of the bootstrap keyed ``key`` (an int or a list of ints; the module
    docstring's "Streams")."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(key)))


def cell_means(groups, n_boot, seed=0):
    """Resample packings within each cell and return the replicas' cell means.

    ``groups``: list of K arrays of shape (n_k, q) (n_k packings, q quantities).
    Returns an array (n_boot, K, q). Deterministic for a given ``seed`` (the generator's key).
    """
    rng = generator(seed)
    K = len(groups)
    q = groups[0].shape[1] if K else 0
    out = np.empty((n_boot, K, q))
    for k, g in enumerate(groups):
        g = np.asarray(g, float)
        n = g.shape[0]
        step = max(1, min(n_boot, (4_000_000 // max(n, 1))))
        for s in range(0, n_boot, step):
            b = min(step, n_boot - s)
            idx = rng.integers(0, n, size=(b, n))
            # how often each packing is drawn in each replica, then one matrix product
            flat = (idx + n * np.arange(b)[:, None]).ravel()
            counts = np.bincount(flat, minlength=b * n).reshape(b, n)
            out[s:s + b, k] = (counts @ g) / n
    return out


def seed_weights(rng, n_seeds, n_boot) -> np.ndarray:
    """How often each of ``n_seeds`` seeds is drawn in each of ``n_boot`` replicas (a multinomial
    draw of ``n_seeds`` seeds with replacement): (n_boot, n_seeds) floats."""
    return rng.multinomial(n_seeds, np.full(n_seeds, 1.0 / n_seeds), size=n_boot).astype(float)


def seed_means(groups, seeds, n_boot, seed=0):
    """Resample whole seeds and return the replicas' cell means, (n_boot, K, q): each replica draws
    the size's seeds with replacement and every cell takes the packings of the seeds drawn, so a
    seed's packings at every energy go together. For packings that share a history along a seed (an
    energy ladder), where resampling within cells (``cell_means``) would count correlated cells as
    independent. ``seeds``: per group, the (n_k,) seed of each packing. A replica that draws none of
    a cell's seeds (a cell missing packings of most seeds) takes the cell's mean (the module
    docstring: ``seed_cell_means`` drops such a replica instead)."""
    rng = generator(seed)
    every = np.unique(np.concatenate([np.asarray(x) for x in seeds])) if len(seeds) else np.zeros(0)
    S = len(every)
    W = seed_weights(rng, S, n_boot) if S else np.zeros((n_boot, 0))
    K = len(groups)
    q = groups[0].shape[1] if K else 0
    out = np.empty((n_boot, K, q))
    for k, (g, sd) in enumerate(zip(groups, seeds)):
        g = np.asarray(g, float)
        M = np.zeros((S, len(g)))
        M[np.searchsorted(every, sd), np.arange(len(g))] = 1.0
        w = W @ M                                   # (n_boot, n_k): how often each packing is drawn
        tot = w.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, k] = (w @ g) / tot[:, None]
        out[tot == 0, k] = g.mean(0)
    return out


def seed_cell_means(counts, sums, n_boot, rng):
    """Resample whole seeds of one size from its packings summed per (seed, cell): ``counts``,
    ``sums`` (S, C) (packings and the sum of one quantity over them). Returns the replicas' packing
    counts and cell means, (B, C) each, of the replicas that hold a packing in every cell: a
    replica that draws none of a cell's seeds is dropped (the module docstring: ``seed_means`` keeps
    it with the cell's mean), so B <= ``n_boot``."""
    K = seed_weights(rng, len(counts), n_boot)  # seed weights per replica
    nb = K @ counts
    with np.errstate(invalid="ignore", divide="ignore"):
        mb = (K @ sums) / nb
    good = np.all(nb > 0, axis=1)
    return nb[good], mb[good]


def clusters(cluster, n_boot, rng):
    """The cluster bootstrap of a statistic of n items in K clusters (``cluster``: (n,) the cluster
    of each item, 0 .. K-1): returns ``stat(fn) -> (value, error)``, ``fn`` taking the indices of the
    items it is computed on. Each replica draws K whole clusters with replacement (drawn here, once,
    so that every statistic sees the same replicas); the error is the replicas' standard deviation,
    NaN ones ignored, and NaN without replicas (``n_boot`` < 2, one cluster) or value."""
    K = len(np.unique(cluster))
    members = [np.flatnonzero(cluster == k) for k in range(K)]
    draws = rng.integers(0, K, size=(n_boot, K)) if n_boot > 1 and K > 1 else None

    def stat(fn):
        value = fn(np.arange(len(cluster)))
        if draws is None or not np.isfinite(value):
            return value, np.nan
        vals = [fn(np.concatenate([members[k] for k in d])) for d in draws]
        return value, float(np.nanstd(vals, ddof=1))

    return stat


def resampled_sums(rows, n_boot, seed):
    """The packings of ``rows`` ((n, m): one row per packing) resampled with replacement, ``n_boot``
    times: each replica's column sums, one at a time."""
    rng = generator(seed)
    n = len(rows)
    for _ in range(n_boot):
        yield rows[rng.integers(0, n, n)].sum(axis=0)
