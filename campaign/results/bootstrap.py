"""Every bootstrap of the reducer, with the random generator each one draws from.

A bootstrap here resamples what is independent in a campaign and recomputes a statistic on every
replica; the error is the spread of the replicas. What is resampled depends on the statistic:

* ``replica_weights`` and ``cell_moments``: the one resampling of the finite-size table and the
  jamming point (docs/REDUCED.md, "Error bars that hold"). The unit drawn is a seed: per cell
  (N_G, E_G) its seeds, the same draw for every variant of the cell (variants made from the same
  random starts are compared packing by packing: a paired bootstrap), and for an energy ladder's
  variant its seeds whole, every energy of a size together (a seed's packings along a ladder share
  a history). ``cell_moments`` turns a cell's draws into its means and covariances per replica, the
  means scaled by ``sqrt(n / (n - 1))`` (a resample's mean scatters by ``(n - 1) / n`` of a cell
  mean's variance); the scaling fits refit every replica with the variance model fitted again to
  the replica (``campaign.results.variance``), so no cell's weight is held from the data.
* ``clusters``: whole clusters of pairs (the variants compared packing by packing,
  ``campaign.results.tradeoff``: the (N, seed) chains);
* ``resampled_sums``: the packings of a cell, their histograms summed (the exponents of
  ``campaign.results.response``).

**Streams.** Every generator is ``generator(key)``: PCG64 seeded by ``SeedSequence(key)``, the key a
list of integers led by the reducer's ``--seed`` (``Settings.boot_seed``):

* ``[boot_seed, 23, N_G, E_G's float64 bits]``: the seeds of cell (N_G, E_G), every variant's;
* ``[boot_seed, 29, N_G]``: the seeds of an energy ladder's size, every energy's;
* ``[boot_seed, 7]``: the variants against the reference, one stream the variants draw from in turn
  (``campaign.results.tradeoff``);
* ``[boot_seed, c]``: the response exponents of the c-th cell; ``[boot_seed, 7, N_G]``: those
  pooled at N_G (``campaign.results.response``).

The table's streams are keyed by what a cell is, not by where it falls in a list, so adding a size,
an energy or a variant to a campaign leaves every other cell's draws as they were. The response's
``[boot_seed, c]`` and ``[boot_seed, 7]`` coincide for c = 7 (and ``SeedSequence`` reads a key of
fewer than four words as if padded with zeros): they resample different data, so each error alone
is as it should be, but the two are not independent draws.
"""

from __future__ import annotations

import numpy as np


def generator(key) -> np.random.Generator:
    """The random generator of the bootstrap keyed ``key`` (an int or a list of ints; the module
    docstring's "Streams")."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(key)))


def seed_weights(rng, n_seeds, n_boot) -> np.ndarray:
    """How often each of ``n_seeds`` seeds is drawn in each of ``n_boot`` replicas (a multinomial
    draw of ``n_seeds`` seeds with replacement): (n_boot, n_seeds) counts, in the smallest unsigned
    integer type that holds ``n_seeds`` (a reduction keeps one such array per cell: a thousand
    replicas of every packing, 8 times less memory than floats; ``cell_moments`` computes in
    float64, exactly). The draws are counted (one ``bincount`` over every replica):
    ``Generator.multinomial`` with as many categories as draws costs a binomial draw per category,
    20 times more at a thousand seeds."""
    kind = np.min_scalar_type(max(n_seeds, 1))
    if n_seeds == 0 or n_boot == 0:
        return np.zeros((n_boot, n_seeds), kind)
    drawn = rng.integers(0, n_seeds, size=(n_boot, n_seeds))
    drawn += np.arange(n_boot)[:, None] * n_seeds
    return np.bincount(drawn.ravel(), minlength=n_boot * n_seeds).reshape(n_boot, n_seeds).astype(kind)


def _energy_word(E) -> int:
    """A cell's energy as a stream key word: its float64 bits (the same energy, the same word)."""
    return int(np.float64(E).view(np.int64)) & 0x7FFFFFFFFFFFFFFF


def replica_weights(grid, seed_of, cells, ladders, n_boot, boot_seed) -> dict:
    """The one resampling of the finite-size table and the jamming point: per cell of ``cells``
    (indices into ``grid``, a ``campaign.results.cells.Grid``), an (n_boot, n_c) array of how often
    each of its packings (in ``grid.packings`` order) is drawn in each replica.

    The unit drawn is a seed: packings of one seed are resampled together wherever they depend on
    each other, and every variant of a cell draws the same seeds, so that variants made from the
    same random starts are compared packing by packing (a paired bootstrap;
    ``campaign.results.protocols``). A cell (N_G, E_G) of independent packings draws its seeds
    (the union over its variants) with replacement; the variants in ``ladders`` (an energy ladder:
    a seed's packings at every energy share one history) draw whole seeds of their size, every
    energy together. Streams: ``[boot_seed, 23, N_G, E_G's bits]`` per cell, ``[boot_seed, 29,
    N_G]`` per ladder size. A variant holding only some of the seeds drawn takes those it holds
    (a replica holding none of its seeds of a cell takes the cell's packings once each)."""
    groups = {}
    for i in cells:
        key = (29, int(grid.cN[i])) if str(grid.cv[i]) in ladders else (23, int(grid.cN[i]), _energy_word(grid.cE[i]))
        groups.setdefault(key, []).append(i)
    out = {}
    for key, members in sorted(groups.items()):
        seeds = np.unique(np.concatenate([seed_of[grid.packings(i)] for i in members]))
        W = seed_weights(generator([boot_seed, *key]), len(seeds), n_boot)
        for i in members:
            w = W[:, np.searchsorted(seeds, seed_of[grid.packings(i)])]
            w[w.sum(1) == 0] = 1.0
            out[i] = w
    return out


def cell_moments(values, weights):
    """A cell's means and covariance in the data and in every replica: ``values`` (n, q) its packings,
    ``weights`` (n_boot, n) from ``replica_weights`` (or None). Returns ``means`` (1 + n_boot, q) and
    ``cov`` (1 + n_boot, q, q) (the sample covariance, n - 1 in the denominator), row 0 the data's.

    A replica's mean is moved from the data's by ``sqrt(n / (n - 1))`` times its deviation: a
    resample's mean scatters by ``(n - 1) / n`` of the variance a cell mean has (13% short in standard
    deviation at 4 packings), which this undoes, so that cells of few packings are not under-weighted
    in the spread of what is fitted to them."""
    n = len(values)
    mean = values.mean(0)
    d = values - mean
    W = np.ones((1, n)) if weights is None else np.vstack([np.ones((1, n)), weights])
    sw = W.sum(1)
    m = (W @ d) / sw[:, None]
    q = d.shape[1]
    m2 = (W @ (d[:, :, None] * d[:, None, :]).reshape(n, q * q)).reshape(-1, q, q) / sw[:, None, None]
    cov = (m2 - m[:, :, None] * m[:, None, :]) * (sw / np.maximum(sw - 1.0, 1.0))[:, None, None]
    means = mean + (np.sqrt(n / (n - 1.0)) if n > 1 else 1.0) * m
    means[0] = mean
    return means, cov


def cell_means(groups, n_boot, seed) -> np.ndarray:
    """Packings resampled within each cell alone (no seeds shared between cells): ``groups`` per
    cell its packings' values (n_c, q); returns the replicas' means (n_boot, cells, q), scaled as
    ``cell_moments`` scales them. For studies of fits on cells of independent packings
    (``experiments/``); the reducer draws ``replica_weights``."""
    rng = generator(seed)
    return np.stack([cell_moments(np.asarray(g, float), seed_weights(rng, len(g), n_boot))[0][1:]
                     for g in groups], 1)


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
