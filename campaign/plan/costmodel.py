"""A cost model that learns from the packings a campaign has finished.

The static model ``campaign.plan.tasks.cost(N, E, protocol)`` is the prior. Finished tasks (their
measured wall time t) fit a correction to it, log-linear in size and in decades of energy:

    log t = log cost(N, E, protocol) + theta_0 + theta_1 (log N - m_N) + theta_2 (log(1 + L) - m_L),
    L = max(0, log10(E_ref / E)),

by Bayesian linear regression with prior theta = 0 (the static model). The features are centred
on the data (m_N, m_L are the means over the finished tasks), so theta_0 is the level where the
data are: timings at one N only move the level and leave the size exponent to the prior, as they
should. The scatter sigma of log t is estimated too; predictions are log-normal means
``exp(mu + sigma^2 / 2)``, so summed estimates of remaining work are unbiased.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from campaign.plan import tasks as _tasks

_PRIOR_SD = np.array([3.0, 0.5, 0.5])  # level (a factor e^3), size exponent, energy exponent
_SIGMA_PRIOR = 0.5   # scatter of log t before any data (about a factor 1.6)
_SIGMA_DOF = 2.0     # weight of that guess, in pseudo-observations


def _raw(N, E):
    N = np.atleast_1d(np.asarray(N, dtype=float))
    E = np.atleast_1d(np.asarray(E, dtype=float))
    L = np.maximum(0.0, np.log10(_tasks.E_REF / E))
    return np.log(N), np.log1p(L)


def _static(N, E, protocols):
    N = np.atleast_1d(N)
    E = np.atleast_1d(E)
    protocols = [None] * len(N) if protocols is None else list(protocols)
    return np.log([_tasks.cost(int(n), float(e), p) for n, e, p in zip(N, E, protocols)])


@dataclass(frozen=True)
class CostModel:
    theta: np.ndarray = field(default_factory=lambda: np.zeros(3))
    centre: tuple = (0.0, 0.0)   # (m_N, m_L) the features are centred on
    sigma: float = _SIGMA_PRIOR  # scatter of log t about the law
    n_points: int = 0            # finished tasks it learnt from

    @classmethod
    def prior(cls) -> "CostModel":
        return cls()

    @classmethod
    def fit(cls, N, E, seconds, protocols=None) -> "CostModel":
        """Update the prior with finished tasks: sizes, target energies, measured wall seconds."""
        seconds = np.atleast_1d(np.asarray(seconds, dtype=float))
        good = np.isfinite(seconds) & (seconds > 0)
        if not np.any(good):
            return cls.prior()
        N = np.atleast_1d(N)[good]
        E = np.atleast_1d(E)[good]
        protos = None if protocols is None else [p for p, g in zip(protocols, good) if g]
        logN, logL = _raw(N, E)
        centre = (float(logN.mean()), float(logL.mean()))
        X = np.stack([np.ones_like(logN), logN - centre[0], logL - centre[1]], axis=1)
        y = np.log(seconds[good]) - _static(N, E, protos)
        sigma = _SIGMA_PRIOR
        for _ in range(5):  # the scatter and the mean, each given the other
            precision = np.diag(1.0 / _PRIOR_SD ** 2) + X.T @ X / sigma ** 2
            theta = np.linalg.solve(precision, X.T @ y / sigma ** 2)
            resid = y - X @ theta
            sigma = math.sqrt((_SIGMA_DOF * _SIGMA_PRIOR ** 2 + resid @ resid) / (_SIGMA_DOF + len(y)))
        return cls(theta=theta, centre=centre, sigma=sigma, n_points=int(len(y)))

    def seconds(self, N, E, protocols=None):
        """Expected seconds of packings of size N at target energy E (arrays, equal length)."""
        logN, logL = _raw(N, E)
        correction = (self.theta[0] + self.theta[1] * (logN - self.centre[0])
                      + self.theta[2] * (logL - self.centre[1]))
        return np.exp(_static(N, E, protocols) + correction + 0.5 * self.sigma ** 2)

    def total_seconds(self, tasks) -> float:
        tasks = list(tasks)
        if not tasks:
            return 0.0
        return float(np.sum(self.seconds([t.N for t in tasks], [t.E for t in tasks],
                                         [dict(t.protocol) for t in tasks])))

    def task_seconds(self, task) -> float:
        return float(self.seconds(task.N, task.E, [dict(task.protocol)])[0])
