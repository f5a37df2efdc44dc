"""The GPU block's layout: the rows of its arrays and of its state, written once for the block
(``kernels.gpu.block``), its control (``kernels.gpu.control``) and the host (``kernels.gpu.batch``).

* ``prm``: a packing's float64 parameters (``P_*``), one row per packing.
* ``st`` / ``sh``: a packing's whole scalar state (``S_*``): the command, the search, the
  minimisation under way, the results, the device's clock, the step's scalars and the block sums;
  ``st`` between launches, ``sh`` (shared memory on a GPU) within one.
* the commands (``C_*``) a phase runs, the events (``EV_*``) the control is told after it.
* the rows of ``fl`` (float64) and ``iv`` (int32).
"""

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
P_BUDGET = 20  # FIRE steps this launch may take (the search stops there and can go on)
N_PARAMS = 21

# the block's state (sh; st between launches): the command, the search, the minimisation under
# way, the results, the device's clock, and the scratch of the step and the sums
(S_CMD, S_PHASE, S_SUB, S_SCALE, S_DELTA, S_LAST_DIR, S_S1, S_G1, S_S2, S_G2, S_SLOPE,
 S_N_BELOW, S_IT, S_NFORCE, S_STEPS, S_E_GUESS, S_STATUS, S_E_LAST, S_W_LAST, S_RES_LAST,
 # the minimisation under way
 S_DT0, S_DT, S_A, S_NPOS, S_NNEG, S_STEP, S_MNFORCE, S_TOL, S_MSTATUS, S_MRES, S_ME, S_SKIN,
 S_RMAX, S_HALF2,
 # the device's clock (ns): the first launch's start, the end, block-time over all launches;
 # launches and steps of this launch
 S_T_FIRST, S_T_END, S_BUSY, S_LAUNCHES, S_LSTEPS, S_T_LAUNCH,
 # the step's scalars, the rebuild flag
 S_MIX, S_RETREAT, S_RB,
 # block sums: energy, contacts, their force, |F|^2, F.v, |v|^2, max |F|^2 (forces); three
 # for the other phases' own; the residual and the non-rattlers; the virial (each pair from
 # both sides)
 S_TE, S_TNC, S_TFS, S_TFF, S_TP, S_TVV, S_TFM, S_X0, S_X1, S_X2, S_RESV, S_NG, S_TW,
 # what every thread reads of the parameters
 S_LX, S_LY, S_XY, S_SIN_TOL, S_NCX, S_NCY, S_ALPHA, S_BUDGET,
 N_ST) = range(65)

# commands (S_CMD)
C_START = 0  # a fresh search: the control sets up the first minimisation
C_BEGIN = 1  # a minimisation from rest: radii from the scale, v = 0, lists rebuilt, forces
C_STEP = 2  # one FIRE step: the move, the lists when due, the forces
C_RESIDUAL = 3  # the rattler-aware force residual
C_VIRIAL = 4  # the virial at the minimisation's end
C_SUSPEND = 5  # stopped at the step budget; the next launch goes on from here
C_DONE = 6
C_RESUME = 7  # (in a launch only) radii, lists from RX, RY, forces: the suspended step's top

# what the control is told after a phase
EV_FORCES = 0
EV_RESUMED = 1  # forces recomputed on resumption: not counted again
EV_RESIDUAL = 2
EV_VIRIAL = 3
EV_OVERFLOW = 4
EV_START = 5

# where the control is in a FIRE step when a residual comes back (S_SUB)
SUB_CHECK = 0
SUB_STALL = 1

# the minimisation's purpose (S_PHASE)
PH_SEARCH = 0
PH_POLISH = 1

#: status of a packing whose cell or neighbour row outgrew its slots (kernels.jamming's codes
#: 0-4 are the CPU search's)
ST_OVERFLOW = 5

#: the reduction scratch's rows (sums and maxima reduced at once)
ROWS = 7
WARP = 32

# rows of fl and iv
VX, VY, FX, FY, RX, RY, R0, R = range(8)
N_FL = 8
NNB, CELL, ALIVE, ALIVE2 = range(4)
N_IV = 4

EXPONENTS = (2.0, 2.5, None)  # the exponents compiled without pow, and any other


def start_state(st):
    """A packing's state row before its first launch (``st`` of ``N_ST`` float64)."""
    st[:] = 0.0
    st[S_CMD] = C_START


def warp_width(nt):
    """Threads in a warp of a block of ``nt`` threads: 32, or ``nt`` when fewer."""
    return WARP if nt >= WARP else nt
