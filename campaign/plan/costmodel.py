"""A cost model that learns from the packings a campaign has finished.

The calibrated model ``campaign.plan.calibration`` (through ``campaign.plan.tasks.cost``, with the
calibration in force) is the prior: its mean seconds per packing m(N, E, protocol), whose median is
``m exp(-s^2 / 2)`` for the calibration's scatter s (``sigma_task``) of ln t between packings.
Finished tasks (their measured wall time t) fit a correction to it, log-linear in size and in
decades of energy:

    log t = log median(N, E, protocol) + theta_0 + theta_1 (log N - m_N) + theta_2 (log(1 + L) - m_L),
    L = max(0, log10(E_ref / E)),

by Bayesian linear regression with prior theta = 0 (the calibrated model). The features are centred
on the data (m_N, m_L are the means over the finished tasks), so theta_0 is the level where the
data are: timings at one N only move the level and leave the size exponent to the prior, as they
should. The scatter sigma of log t is estimated too (its prior: the calibration's s); predictions
are log-normal means ``exp(mu + sigma^2 / 2)``, so summed estimates of remaining work are unbiased,
and before any data they are the calibrated means. A ladder step (``parent_E``) is priced as one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from campaign.plan import calibration
from campaign.plan import tasks as _tasks

_PRIOR_SD = np.array([3.0, 0.5, 0.5])  # level (a factor e^3), size exponent, energy exponent
_SIGMA_DOF = 2.0     # weight of the calibration's scatter, in pseudo-observations


def _sigma_prior() -> float:
    """The scatter of log t before any data: the calibration's (about 0.3, a factor 1.35)."""
    return max(0.05, calibration.active().sigma_task)


def _raw(N, E):
    N = np.atleast_1d(np.asarray(N, dtype=float))
    E = np.atleast_1d(np.asarray(E, dtype=float))
    L = np.maximum(0.0, np.log10(_tasks.E_REF / E))
    return np.log(N), np.log1p(L)


def _static(N, E, protocols, parents=None, exponents=None):
    """ln of the calibrated median seconds (mean exp(-s^2/2)) of each packing."""
    N = np.atleast_1d(N)
    E = np.atleast_1d(E)
    protocols = [None] * len(N) if protocols is None else list(protocols)
    parents = [None] * len(N) if parents is None else list(parents)
    exponents = [2.0] * len(N) if exponents is None else list(exponents)
    half = 0.5 * _sigma_prior() ** 2
    return np.log([_tasks.cost(int(n), float(e), p, float(a), None if pe is None or pe != pe else float(pe))
                   for n, e, p, pe, a in zip(N, E, protocols, parents, exponents)]) - half


@dataclass(frozen=True)
class CostModel:
    theta: np.ndarray = field(default_factory=lambda: np.zeros(3))
    centre: tuple = (0.0, 0.0)   # (m_N, m_L) the features are centred on
    sigma: float | None = None   # scatter of log t about the law (None: the calibration's)
    n_points: int = 0            # finished tasks it learnt from

    @classmethod
    def prior(cls) -> "CostModel":
        return cls()

    @property
    def scatter(self) -> float:
        return _sigma_prior() if self.sigma is None else self.sigma

    @classmethod
    def fit(cls, N, E, seconds, protocols=None, parents=None, exponents=None) -> "CostModel":
        """Update the prior with finished tasks: sizes, target energies, measured wall seconds (and
        their protocols, ladder parents' energies, potential exponents)."""
        seconds = np.atleast_1d(np.asarray(seconds, dtype=float))
        good = np.isfinite(seconds) & (seconds > 0)
        if not np.any(good):
            return cls.prior()
        N = np.atleast_1d(N)[good]
        E = np.atleast_1d(E)[good]
        pick = (lambda xs: None if xs is None else [x for x, g in zip(xs, good) if g])
        logN, logL = _raw(N, E)
        centre = (float(logN.mean()), float(logL.mean()))
        X = np.stack([np.ones_like(logN), logN - centre[0], logL - centre[1]], axis=1)
        y = np.log(seconds[good]) - _static(N, E, pick(protocols), pick(parents), pick(exponents))
        s0 = _sigma_prior()
        sigma = s0
        for _ in range(5):  # the scatter and the mean, each given the other
            precision = np.diag(1.0 / _PRIOR_SD ** 2) + X.T @ X / sigma ** 2
            theta = np.linalg.solve(precision, X.T @ y / sigma ** 2)
            resid = y - X @ theta
            sigma = math.sqrt((_SIGMA_DOF * s0 ** 2 + resid @ resid) / (_SIGMA_DOF + len(y)))
        return cls(theta=theta, centre=centre, sigma=sigma, n_points=int(len(y)))

    def seconds(self, N, E, protocols=None, parents=None, exponents=None):
        """Expected seconds of packings of size N at target energy E (arrays, equal length)."""
        logN, logL = _raw(N, E)
        correction = (self.theta[0] + self.theta[1] * (logN - self.centre[0])
                      + self.theta[2] * (logL - self.centre[1]))
        return np.exp(_static(N, E, protocols, parents, exponents) + correction + 0.5 * self.scatter ** 2)

    def total_seconds(self, tasks) -> float:
        tasks = list(tasks)
        if not tasks:
            return 0.0
        return float(np.sum(self.seconds([t.N for t in tasks], [t.E for t in tasks],
                                         [dict(t.protocol) for t in tasks], [t.parent_E for t in tasks],
                                         [t.exponent for t in tasks])))

    def task_seconds(self, task) -> float:
        return float(self.seconds(task.N, task.E, [dict(task.protocol)], [task.parent_E], [task.exponent])[0])
