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
