"""Thread 0's part of the GPU block: after every phase, the next command and its scalars.

``make_control(jit)`` compiles, with ``jit``, the control of ``kernels.gpu.block``'s search:
FIRE 2.0's tests and adaptation (``kernels.fire._fire_run``'s), the O'Hern search's polish, next
radius scale and end (``kernels.protocol._ohern_search``'s rules, ``kernels.rules``), all of it
on the block's state row ``sh`` (``kernels.gpu.state``), which only thread 0 writes between two
barriers; every other thread reads the command it leaves there.
"""

import math
from types import SimpleNamespace

from kernels import rules
from kernels.gpu.state import (C_BEGIN, C_DONE, C_RESIDUAL, C_STEP, C_SUSPEND, C_VIRIAL,
                               EV_FORCES, EV_OVERFLOW, EV_RESIDUAL, EV_START, EV_VIRIAL,
                               PH_POLISH, PH_SEARCH, P_ALPHA, P_DELTA, P_ENERGY_STEP, P_E_MIN,
                               P_MAX_RADIUS, P_MAX_SEARCH, P_MAX_STEPS, P_MEAN_D, P_RMAX, P_RULE,
                               P_SEARCH_TOL, P_SKIN, P_TOL, P_WINDOW, ST_OVERFLOW, SUB_CHECK,
                               SUB_STALL, S_A, S_BUDGET, S_CMD, S_DELTA, S_DT, S_DT0, S_E_GUESS,
                               S_E_LAST, S_G1, S_G2, S_HALF2, S_IT, S_LAST_DIR, S_LSTEPS, S_ME,
                               S_MIX, S_MNFORCE, S_MRES, S_MSTATUS, S_NFORCE, S_NNEG, S_NPOS,
                               S_N_BELOW, S_PHASE, S_RB, S_RESV, S_RES_LAST, S_RETREAT, S_RMAX,
                               S_S1, S_S2, S_SCALE, S_SKIN, S_SLOPE, S_STATUS, S_STEP, S_STEPS,
                               S_SUB, S_TE, S_TFF, S_TFM, S_TFS, S_TNC, S_TOL, S_TP, S_TVV, S_TW,
                               S_W_LAST)


def make_control(jit):
    """Thread 0's control compiled with ``jit``: ``control(sh, prm, n, event)`` writes the next
    command (``sh[S_CMD]``) and its scalars after the phase that raised ``event``."""
    dt_from_diameter = jit(rules.dt_from_diameter)
    fire_adapt = jit(rules.fire_adapt)
    search_step = jit(rules.search_step)
    search_targets = jit(rules.search_targets)
    search_start = jit(rules.search_start)

    @jit
    def begin(sh, prm, tol, fresh):
        """Thread 0: a minimisation from rest at the current scale (``fresh``: its own starting
        time step, else the last one's: a polish at the same radii)."""
        scale = sh[S_SCALE]
        mean_d = prm[P_MEAN_D]
        skin = prm[P_SKIN] * mean_d * scale
        sh[S_SKIN] = skin
        sh[S_RMAX] = prm[P_RMAX] * scale
        sh[S_HALF2] = 0.25 * skin * skin
        if fresh:
            sh[S_DT0] = dt_from_diameter(mean_d * scale, prm[P_ALPHA], sh[S_E_GUESS])
        sh[S_DT] = sh[S_DT0]
        sh[S_A] = rules.A_START
        sh[S_NPOS] = 0.0
        sh[S_NNEG] = 0.0
        sh[S_STEP] = 0.0
        sh[S_MNFORCE] = 0.0
        sh[S_TOL] = tol
        sh[S_MRES] = math.inf
        sh[S_RB] = 0.0
        sh[S_CMD] = C_BEGIN

    @jit
    def end_minimisation(sh, status, res):
        """Thread 0: the minimisation stops with ``status``; its virial next."""
        sh[S_MSTATUS] = status
        sh[S_MRES] = res
        sh[S_CMD] = C_VIRIAL

    @jit
    def done(sh, status):
        sh[S_STATUS] = status
        sh[S_CMD] = C_DONE

    @jit
    def advance(sh, prm):
        """Thread 0: past the tests, one FIRE step (``kernels.fire._fire_run``'s), or the end of
        the minimisation at its step bound or in a stall."""
        step = int(sh[S_STEP])
        if step >= int(prm[P_MAX_STEPS]):
            end_minimisation(sh, rules.MAX_STEPS, sh[S_MRES])
            return
        step += 1
        sh[S_STEP] = step
        sh[S_LSTEPS] += 1.0
        p = sh[S_TP]
        dt0 = sh[S_DT0]
        n_pos, n_neg, dt, a = fire_adapt(p, step, int(sh[S_NPOS]), int(sh[S_NNEG]), sh[S_DT],
                                         sh[S_A], rules.DT_MIN_FACTOR * dt0,
                                         rules.DT_MAX_FACTOR * dt0)
        sh[S_NPOS] = n_pos
        sh[S_NNEG] = n_neg
        sh[S_DT] = dt
        sh[S_A] = a
        if p <= 0.0 and n_neg > rules.N_NEG_MAX:
            sh[S_SUB] = SUB_STALL
            sh[S_CMD] = C_RESIDUAL
            return
        ff = sh[S_TFF]
        # |v + dt F|^2 from the sums: v = 0 after a retreat
        if p <= 0.0:
            vv = dt * dt * ff
            sh[S_RETREAT] = 1.0
        else:
            vv = sh[S_TVV] + 2.0 * dt * p + dt * dt * ff
            sh[S_RETREAT] = 0.0
        sh[S_MIX] = a * math.sqrt(vv / ff) if ff > 0.0 else 0.0
        sh[S_CMD] = C_STEP

    @jit
    def evaluate(sh, prm, n):
        """Thread 0: a minimisation has ended (its virial computed): polish it, take the
        search's next radius scale (``kernels.protocol._ohern_search``'s rules) or finish."""
        st = int(sh[S_MSTATUS])
        e = sh[S_ME]
        w = 0.5 * sh[S_TW]
        res = sh[S_MRES]
        sh[S_NFORCE] += sh[S_MNFORCE]
        sh[S_STEPS] += sh[S_STEP]
        e_min = prm[P_E_MIN]
        tol = prm[P_TOL]
        search_tol = prm[P_SEARCH_TOL]
        e_max, inv_a, g_target, x_per_g = search_targets(e_min, prm[P_WINDOW], prm[P_ALPHA])
        eg = e / n
        if (sh[S_PHASE] == PH_SEARCH and st == rules.CONVERGED and e_min <= eg <= e_max
                and search_tol > tol):
            # polish to the final tolerance at the same radii
            sh[S_PHASE] = PH_POLISH
            begin(sh, prm, tol, False)
            return
        sh[S_PHASE] = PH_SEARCH
        sh[S_E_LAST] = e
        sh[S_W_LAST] = w
        sh[S_RES_LAST] = res
        if st == rules.CONVERGED and eg > 0.0:
            sh[S_E_GUESS] = eg
        if st == rules.MAX_STEPS:
            done(sh, 2)  # max_steps
            return
        if st != rules.CONVERGED and st != rules.BELOW:
            done(sh, 3)  # stalled
            return
        if st == rules.CONVERGED and e_min <= eg <= e_max:
            done(sh, 0)  # converged
            return
        if sh[S_IT] >= prm[P_MAX_SEARCH]:
            done(sh, 1)  # max_search
            return
        scale = sh[S_SCALE]
        delta0 = prm[P_DELTA]
        new, delta, last_dir, s1, g1, s2, g2, slope, n_below = search_step(
            int(prm[P_RULE]), st == rules.CONVERGED and eg > 0.0,
            st == rules.BELOW or eg < e_min, eg, scale, sh[S_DELTA], int(sh[S_LAST_DIR]),
            sh[S_S1], sh[S_G1], sh[S_S2], sh[S_G2], sh[S_SLOPE], int(sh[S_N_BELOW]), delta0,
            g_target, x_per_g, inv_a, prm[P_ENERGY_STEP])
        sh[S_DELTA] = delta
        sh[S_LAST_DIR] = last_dir
        sh[S_S1] = s1
        sh[S_G1] = g1
        sh[S_S2] = s2
        sh[S_G2] = g2
        sh[S_SLOPE] = slope
        sh[S_N_BELOW] = n_below
        if new == scale:
            done(sh, 1)  # max_search: the step is below the scale's float64 resolution
            return
        if new * prm[P_RMAX] > prm[P_MAX_RADIUS]:
            done(sh, 4)  # too_dense
            return
        sh[S_SCALE] = new
        sh[S_IT] += 1.0
        begin(sh, prm, search_tol, True)

    @jit
    def control(sh, prm, n, event):
        """Thread 0, after every phase: the next command and its scalars into ``sh``."""
        if event == EV_START:
            delta, last_dir, s1, g1, s2, g2, slope, n_below = search_start(prm[P_DELTA])
            sh[S_PHASE] = PH_SEARCH
            sh[S_SCALE] = 1.0
            sh[S_DELTA] = delta
            sh[S_LAST_DIR] = last_dir
            sh[S_S1] = s1
            sh[S_G1] = g1
            sh[S_S2] = s2
            sh[S_G2] = g2
            sh[S_SLOPE] = slope
            sh[S_N_BELOW] = n_below
            sh[S_IT] = 1.0
            sh[S_NFORCE] = 0.0
            sh[S_STEPS] = 0.0
            sh[S_STATUS] = 1.0
            sh[S_RES_LAST] = math.inf
            sh[S_E_GUESS] = max(prm[P_E_MIN], rules.E_FIRST_GUESS)
            begin(sh, prm, prm[P_SEARCH_TOL], True)
            return
        if event == EV_OVERFLOW:
            sh[S_NFORCE] += sh[S_MNFORCE]
            sh[S_STEPS] += sh[S_STEP]
            sh[S_E_LAST] = sh[S_ME]
            done(sh, ST_OVERFLOW)
            return
        if event == EV_VIRIAL:
            evaluate(sh, prm, n)
            return
        if event == EV_RESIDUAL:
            res = sh[S_RESV]
            if sh[S_SUB] == SUB_STALL:
                end_minimisation(sh, rules.STALLED, res)
                return
            sh[S_MRES] = res
            if res < sh[S_TOL]:
                end_minimisation(sh, rules.CONVERGED, res)
                return
            advance(sh, prm)
            return
        # the forces of a step: first the budget, then FIRE's tests (kernels.fire._fire_run)
        if event == EV_FORCES:
            sh[S_MNFORCE] += 1.0
        if sh[S_LSTEPS] >= sh[S_BUDGET]:
            sh[S_CMD] = C_SUSPEND
            return
        energy = 0.5 * sh[S_TE]
        nc = 0.5 * sh[S_TNC]
        fs = 0.5 * sh[S_TFS]
        sh[S_ME] = energy
        e_abort = rules.ABORT_FRACTION * prm[P_E_MIN] * n
        if e_abort > 0.0 and energy < e_abort:
            end_minimisation(sh, rules.BELOW, -1.0)
            return
        if nc == 0.0:
            end_minimisation(sh, rules.CONVERGED, 0.0)
            return
        mean_f = fs / nc
        bound = math.sqrt(sh[S_TFM]) / mean_f if mean_f > 0.0 else 0.0
        step = int(sh[S_STEP])
        if (bound < sh[S_TOL] or step % rules.CHECK_EVERY == 0
                or step >= int(prm[P_MAX_STEPS])):
            sh[S_SUB] = SUB_CHECK
            sh[S_CMD] = C_RESIDUAL
            return
        advance(sh, prm)

    return SimpleNamespace(control=control)
