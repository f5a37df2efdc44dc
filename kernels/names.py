"""Names of the observables and the histograms they produce (no numba: cheap to import).

The campaign's spec validation and the analysis kernels both read this one table
(docs/CONTRACTS.md, ``kernels.analyze``).
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
}
HISTOGRAMS = tuple(h for names in OBSERVABLES.values() for h in names)
