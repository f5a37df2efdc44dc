"""The minimisers' rules, written once for every target: FIRE 2.0's constants, status codes and
time-step adaptation, the starting time step, and the O'Hern search's next radius scale.

Every function here is plain Python on scalars (no arrays, no allocation, ``math`` only), so
that one definition compiles for the CPU kernels (``numba.njit``: ``kernels.fire``,
``kernels.protocol``, ``kernels.barostat``, ``kernels.cellrelax``) and for the GPU block
(``numba.cuda.jit(device=True)``: ``kernels.gpu.block``). The CPU modules bind their jitted
copies (``fire_adapt``, ``search_step`` ...); a rule changed here changes every minimiser.

FIRE 2.0 (Guenole et al., Comput. Mater. Sci. 175, 109584 (2020)): after ``N_DELAY`` downhill
steps the time step grows by ``F_INC`` (up to ``DT_MAX_FACTOR dt0``) and the mixing ``a`` shrinks
by ``F_A``; a step with non-positive power ``P = F.v`` resets ``a`` to ``A_START`` and, past the
first ``N_DELAY`` steps, halves the time step (not below ``DT_MIN_FACTOR dt0``); the minimiser
then retreats half a step and zeroes the velocities, and stops as stalled after ``N_NEG_MAX``
consecutive such steps.
"""

import math

N_DELAY = 20
F_INC = 1.1
F_DEC = 0.5
A_START = 0.25
F_A = 0.99
DT_MAX_FACTOR = 10.0
DT_MIN_FACTOR = 0.02
N_NEG_MAX = 2000
CHECK_EVERY = 100  # steps between the rattler-aware residual checks of a minimisation
DT_FACTOR = 0.04  # initial FIRE time step in units of 1/sqrt(stiffness), see dt_from_diameter

# status codes of one minimisation (every minimiser)
CONVERGED = 0
MAX_STEPS = 1
STALLED = 2
BELOW = 3  # the energy fell below the caller's abort level (the minimum is lower still)
STATUS_NAMES = ("converged", "max_steps", "stalled", "below")

# the O'Hern search's rules (kernels.protocol, kernels.barostat, the GPU block)
AIM = 0.5  # the secant rule aims at E_min (1 + AIM window)
ABORT_FRACTION = 0.5  # stop a minimisation once E_G < ABORT_FRACTION E_min
# The first minimisation relaxes the random start (overlaps up to x ~ 0.2): its time step is
# sized for an energy of at least this much, not for the target. For alpha > 2 a step sized for
# E_G ~ 1e-22 is ~1000 times too long there and FIRE never converges; for alpha = 2 the step does
# not depend on the energy. Later minimisations use the energy of the latest jammed minimum.
E_FIRST_GUESS = 1e-8
SEARCH_HALVING = 0
SEARCH_SECANT = 1
SEARCH_PAPER = 2
SEARCH_NAMES = ("halving", "secant", "paper")


def fire_adapt(p, step, n_pos, n_neg, dt, a, dt_min, dt_max):
    """FIRE 2.0's time step and mixing after a step of power ``p``: after ``N_DELAY``
    downhill steps grow ``dt`` and shrink ``a``; on a non-positive power count it (a stall
    past ``N_NEG_MAX``) and, past the first ``N_DELAY`` steps, shrink ``dt`` and reset ``a``
    (the caller then retreats half a step). Returns ``(n_pos, n_neg, dt, a)``."""
    if p > 0.0:
        n_pos += 1
        n_neg = 0
        if n_pos > N_DELAY:
            dt = min(dt * F_INC, dt_max)
            a *= F_A
    else:
        n_pos = 0
        n_neg += 1
        if step >= N_DELAY:
            if dt * F_DEC >= dt_min:
                dt *= F_DEC
            a = A_START
    return n_pos, n_neg, dt, a


def dt_from_diameter(s, alpha, e_per_disk):
    """Initial FIRE time step ``DT_FACTOR / sqrt(k)`` (unit masses) for disks of mean diameter
    ``s`` at energy ``e_per_disk`` per disk.

    ``k = (alpha - 1) x^(alpha - 2) / s^2`` is the stiffness of a contact between two disks of
    mean diameter ``s`` at overlap ``x = 3 (alpha E)^(1/alpha)`` (a few times the typical
    overlap at energy ``E`` per disk, at most 0.2). With ``dt_max = 10 dt0`` the factor 0.04
    keeps the fastest harmonic mode stable; 0.06 already is not.
    """
    x = 3.0 * (alpha * max(e_per_disk, 1e-300)) ** (1.0 / alpha)
    if x > 0.2:
        x = 0.2
    k = (alpha - 1.0) * x ** (alpha - 2.0) / (s * s)
    return DT_FACTOR / math.sqrt(k)


def search_targets(e_min, window, alpha):
    """The search's fixed numbers for the window ``[e_min, e_min (1 + window)]``: ``(e_max,
    1 / alpha, g_target, x_per_g)``. The secant rule aims at the upper part of the window
    (decompression tends to undershoot): ``g_target = (e_min (1 + AIM window))^(1/alpha)``;
    ``x = (alpha E / 2)^(1/alpha)`` is the typical relative overlap at energy ``E`` per disk."""
    inv_a = 1.0 / alpha
    return (e_min * (1.0 + window), inv_a, (e_min * (1.0 + AIM * window)) ** inv_a,
            (0.5 * alpha) ** inv_a)


def search_start(delta0):
    """The search state of ``search_step`` before the first minimisation: ``(delta, last_dir, s1,
    g1, s2, g2, slope, n_below)`` (no jammed minimum yet: ``s1 = s2 = -1``; slope unknown: 0)."""
    return delta0, 0, -1.0, 0.0, -1.0, 0.0, 0.0, 0


def search_step(rule, jammed, below, eg, scale, delta, last_dir, s1, g1, s2, g2, slope, n_below,
                delta0, g_target, x_per_g, inv_a, energy_step):
    """The O'Hern search's next radius scale after a minimisation (``kernels.protocol`` gives
    the rules in words).

    ``jammed``: the minimisation converged to a force-balanced minimum with ``E_G = eg > 0``;
    ``below``: it was aborted below the window, or converged below it. The search state
    ``(delta, last_dir, s1, g1, s2, g2, slope, n_below)`` is the halving rules' step and last
    direction and the secant rule's two latest jammed minima ``(s, E_G^(1/alpha))``, its slope
    and the count of consecutive minimisations below the window without a jammed minimum.

    Returns ``(new_scale, delta, last_dir, s1, g1, s2, g2, slope, n_below)``.
    """
    direction = 1 if below else -1
    if rule == SEARCH_HALVING or rule == SEARCH_PAPER:
        if rule == SEARCH_HALVING and last_dir != 0 and direction != last_dir:
            delta *= 0.5
        last_dir = direction
        if direction > 0:
            new = scale * (1.0 + delta)
        else:
            new = scale / (1.0 + delta)
        if rule == SEARCH_PAPER:
            delta *= 0.5  # after every minimisation, whatever the direction
        return new, delta, last_dir, s1, g1, s2, g2, slope, n_below
    if jammed:
        # a jammed minimum: refit g = slope (scale - scale_J)
        n_below = 0
        s2 = s1
        g2 = g1
        s1 = scale
        g1 = eg ** inv_a
        # one-point model: scale_J ~ scale (1 - x)
        c1 = 1.0 / (scale * x_per_g)
        slope = c1
        if s2 > 0.0 and s1 != s2:
            c2 = (g1 - g2) / (s1 - s2)
            if 0.2 * c1 < c2 < 5.0 * c1:
                slope = c2
        g_goal = g_target
        if g1 > g_target and g1 * energy_step ** inv_a > g_goal:
            g_goal = g1 * energy_step ** inv_a
        new = s1 + (g_goal - g1) / slope
    else:
        # below the window without a force-balanced minimum (unjammed, or aborted at
        # E < E_min / 2): grow, doubling the step each time
        n_below += 1
        s1 = -1.0
        s2 = -1.0
        if slope > 0.0:
            g_now = max(eg, 0.0) ** inv_a
            new = scale + 2.0 ** (n_below - 1) * (g_target - g_now) / slope
        else:
            new = scale * (1.0 + delta0)
    if new > scale * (1.0 + delta0):
        new = scale * (1.0 + delta0)
    if new < scale / (1.0 + delta0):
        new = scale / (1.0 + delta0)
    return new, delta, last_dir, s1, g1, s2, g2, slope, n_below
