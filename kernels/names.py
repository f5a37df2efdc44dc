"""Names of the observables and the histograms they produce, of the continuous size
distributions, and the largest tilt of a periodic cell (no numba: cheap to import).

The campaign's spec validation and the kernels both read these tables
(docs/CONTRACTS.md, ``kernels.analyze``, ``kernels.jam``).
"""

#: observable name -> the histograms it produces
OBSERVABLES = {
    "scalars": (),
    "contact_angles": ("contact_angle",),
    "contact_lengths": ("contact_length",),
    "connectivity": ("z_g", "z_v"),
    "edge_triangles": ("alpha_e",),
    "void_areas": ("alpha_v",),
    "fictitious": ("fictitious_length",),
    "radial_grains": ("radial_grains",),
    "radial_contacts": ("radial_contacts",),
    # linear response (kernels.response, docs/RESPONSE.md): computed only when named
    "moduli": (),
    "modes": ("omega",),
    "gaps": ("gap", "force", "force_extended"),
}
HISTOGRAMS = tuple(h for names in OBSERVABLES.values() for h in names)
#: The linear-response observables: they cost more than the contact network's (a sparse
#: factorisation, a spectrum) and are computed only when asked for by name.
RESPONSE_OBSERVABLES = ("moduli", "modes", "gaps")
#: What ``kernels.analyze(observables=None)`` computes: every contact-network observable.
DEFAULT_OBSERVABLES = tuple(o for o in OBSERVABLES if o not in RESPONSE_OBSERVABLES)

#: Continuous size distributions (``kernels.jam(..., sizes=(name, polydispersity))``): relative
#: radii of mean 1 and standard deviation ``polydispersity``, drawn per disk from the task's stream.
SIZE_DISTRIBUTIONS = ("uniform", "lognormal")
#: Largest polydispersity accepted: at 0.5 the uniform distribution's smallest disk is 0.13
#: of the mean, the log-normal's 1st percentile 0.28; wider ones make most small disks rattlers.
MAX_POLYDISPERSITY = 0.5

#: Largest |xy| of a tilted cell ``[Lx, Ly, xy]`` (``kernels.space``) the kernels accept and the
#: configuration readers take as given: ``xy - Lx/Ly`` describes the same lattice (``b -> b - a``),
#: so any cell can be reduced; beyond 1 its sides meet at angles that only waste cell-list work.
MAX_TILT = 1.0

#: The protocol's choices of how a packing is made, by name (``kernels.jam`` and the spec's
#: ``protocol``); the kernels' codes are the positions in these tuples.
MINIMIZER_NAMES = ("fire", "cg")
STOP_RULES = ("force", "energy")
ROUTES = ("ohern", "pressure")
ENDGAME_NAMES = ("none", "newton")
CELL_NAMES = ("fixed", "shear")
#: The choices in the order of ``RUNNABLE``'s rows, each with its default.
CHOICES = {"route": ROUTES, "minimizer": MINIMIZER_NAMES, "stop": STOP_RULES, "endgame": ENDGAME_NAMES,
           "cell": CELL_NAMES}
CHOICE_DEFAULTS = {k: names[0] for k, names in CHOICES.items()}

#: The combinations of choices the kernels run, one jitted search each: the O'Hern route's rows
#: are the entries of ``kernels.protocol.OHERN_CORES`` (keyed by the codes of minimiser, endgame
#: and cell; the stop rule is an argument of the CG search), the pressure route's is
#: ``kernels.barostat``'s. kernels.protocol refuses to import if its table and this one part.
RUNNABLE = (
    ("ohern", "fire", "force", "none", "fixed"),
    ("ohern", "cg", "force", "none", "fixed"),
    ("ohern", "cg", "energy", "none", "fixed"),
    ("ohern", "fire", "force", "newton", "fixed"),
    ("ohern", "fire", "force", "none", "shear"),
    ("pressure", "fire", "force", "none", "fixed"),
)
#: What each non-default choice does, for the message that refuses a combination without it.
_WHY = {("stop", "energy"): "counts conjugate-gradient steps",
        ("route", "pressure"): "relaxes with FIRE toward a pressure",
        ("endgame", "newton"): "finishes the FIRE minimisations of the O'Hern search",
        ("cell", "shear"): "relaxes the cell with the FIRE minimisations of the O'Hern search"}


def protocol_problem(choice, shown=None):
    """None if the kernels run the combination ``choice`` (a mapping of some of ``CHOICES``' keys
    to names; the others take their defaults), else ``(key, message)``: the first non-default
    choice (the stop rule, cell, endgame, route, then the minimiser) whose rows of ``RUNNABLE``
    do not hold the others, and a sentence saying what it needs. ``shown``: the names to print
    instead, where a caller's name for a choice differs (``endgame: auto``). Unknown names are
    the caller's to refuse first."""
    full = dict(CHOICE_DEFAULTS, **{k: v for k, v in choice.items() if k in CHOICES})
    if tuple(full[k] for k in CHOICES) in RUNNABLE:
        return None
    shown = dict(full, **(shown or {}))
    keys = list(CHOICES)
    for key in ("stop", "cell", "endgame", "route", "minimizer"):
        if full[key] == CHOICE_DEFAULTS[key] and key != "minimizer":
            continue
        rows = [dict(zip(keys, row)) for row in RUNNABLE if row[keys.index(key)] == full[key]]
        fixed = [k for k in ("minimizer", "stop", "route", "endgame", "cell")
                 if k != key and len({r[k] for r in rows}) == 1]
        if all(rows[0][k] == full[k] for k in fixed):
            continue  # what it needs is there: another choice is to blame
        needs = [f"{k} {rows[0][k]!r}" for k in fixed]
        needs = " and ".join([", ".join(needs[:-1]), needs[-1]] if len(needs) > 1 else needs)
        got = ", ".join(f"{k} {shown[k]!r}" for k in fixed if full[k] != rows[0][k])
        return key, f"{key} {shown[key]!r} {_WHY.get((key, full[key]), 'runs')}: it needs {needs}; got {got}"
    raise AssertionError(f"no rule refuses {full}")  # every combination outside RUNNABLE has one
