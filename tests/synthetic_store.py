"""Write a synthetic campaign file in the layout of docs/CONTRACTS.md ("The HDF5 store").

The per-packing scalars follow known laws, so the reducer's fits can be checked
against the truth:

    A_G   = A_inf + a_N / N + c_A E_G**beta_A (1 + k_A E_G**omega_A) + noise(sigma_A / sqrt(N))
    psi_O = P_inf + p_N / N + c_P E_G**beta_P + noise(sigma_P / sqrt(N))
    delta_Z = c_Z E_G**(1/(2 alpha)) (1 + noise)     (alpha = 2 by default: E_G**(1/4))
    phi     = phi_inf + phi_N / N + c_phi E_G**(1/alpha) + noise(sigma_phi / sqrt(N));  N_R ~ Bin(N, f_R)

so ``A_G - A* = B delta_Z**beta_Z`` with ``beta_Z = 2 alpha beta_A`` (``Truth.jamming``);
``k_A`` (0 by default) adds a correction to scaling of exponent ``omega_A``.
``SyntheticCampaign.variant_truth`` gives variants their own truths; the spec text then lists
the variants, with a ``system.potential.exponent`` override where the truth's alpha differs
from the base's (and ``variant_system``, any other ``system`` override).

Histograms are Poisson counts around fixed shapes (uniform angles with the
three-disk peaks, etc.); they only need to be plausible and additive.

Used by tests/results/test_reduce.py, tests/report/test_plots.py and benchmarks/bench_reduce.py.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import h5py
import numpy as np

SPEC_YAML = """\
name: synthetic
seed: 1
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
grid:
  N_G: [64, 128]
  E_G: [1.0e-4]
  seeds: 4
"""


@dataclass
class Truth:
    A_inf: float = 0.446
    a_N: float = -0.6
    c_A: float = 0.5
    beta_A: float = 0.28
    sigma_A: float = 0.03
    k_A: float = 0.0       # correction to scaling: c_A E**beta_A (1 + k_A E**omega_A)
    omega_A: float = 0.25
    P_inf: float = 0.369
    p_N: float = -0.4
    c_P: float = 0.6
    beta_P: float = 0.27
    sigma_P: float = 0.05
    c_Z: float = 3.0
    sigma_Z: float = 0.05
    iso_E: float = 0.0   # below this E_G every packing is isostatic: delta_Z = 0 exactly
    alpha: float = 2.0   # potential exponent: delta_Z ~ E_G**(1/(2 alpha))
    z_exponent: float | None = None  # exponent of delta_Z in E_G; None: 1/(2 alpha)
    # the finite-size plateau (0: none): delta_Z = c_Z E^z_power s with
    # s = 1 - exp(-(N c_Z E^z_power / plateau)^2), and A_G - A*, psi_O - P* follow delta_Z (their
    # laws in delta_Z hold at every size, as measured), so below N_G delta_Z ~ plateau both saturate
    plateau: float = 0.0
    # the jamming point: phi = phi_inf + phi_N / N + c_phi E_G**(1/alpha) + noise(sigma_phi / sqrt(N))
    # (linear in the typical overlap); N_R ~ Binomial(N, f_R)
    phi_inf: float = 0.84
    phi_N: float = 0.0
    c_phi: float = 0.5
    sigma_phi: float = 0.0
    f_R: float = 0.04

    @classmethod
    def jamming(cls, alpha, beta_Z, **kw):
        """The truth of a system obeying jamming scaling with exponent ``alpha`` and a given
        ``beta_Z``: ``beta_E = beta_Z / (2 alpha)``."""
        return cls(alpha=alpha, beta_A=beta_Z / (2.0 * alpha), **kw)

    @property
    def z_power(self):
        return 1.0 / (2.0 * self.alpha) if self.z_exponent is None else self.z_exponent

    @property
    def beta_Z(self):
        """The exponent of A_G - A* against delta_Z."""
        return self.beta_A / self.z_power

    def suppression(self, N, E):
        """The finite-size factor s of delta_Z (1 without a plateau)."""
        if self.plateau <= 0:
            return np.ones_like(np.asarray(E, float))
        return 1.0 - np.exp(-(np.asarray(N, float) * self.c_Z * np.asarray(E, float) ** self.z_power
                              / self.plateau) ** 2)

    def A_star(self, N):
        return self.A_inf + self.a_N / np.asarray(N, float)

    def P_star(self, N):
        return self.P_inf + self.p_N / np.asarray(N, float)


# The same bins as kernels.analysis.DEFAULT_BINS (about 2100 per packing).
DEFAULT_EDGES = {
    "contact_angle": np.linspace(0.0, np.pi, 181),
    "contact_length": np.linspace(0.0, 8.0, 161),
    "z_g": np.arange(-0.5, 21.0, 1.0),
    "z_v": np.arange(-0.5, 41.0, 1.0),
    "alpha_e": np.linspace(0.0, 0.5, 201),
    "alpha_v": np.linspace(0.0, 4.0, 401),
    "fictitious_length": np.linspace(0.0, 3.0, 301),
    "radial_grains": np.linspace(0.0, 8.0, 401),
    "radial_contacts": np.linspace(0.0, 8.0, 401),
}


def _shape(name, edges):
    """A plausible expected-count profile (per packing, before scaling by N)."""
    c = 0.5 * (edges[1:] + edges[:-1])
    if name == "contact_angle":
        p = np.where(c < np.pi * 0.9, 1.0, 0.05)
        for t in (1.245653, 1.141021, 1.047198, 0.947970, 0.859551):
            p = p + 3.0 * np.exp(-0.5 * ((c - t) / 0.01) ** 2)
        return p * (c > 0.6)
    if name == "contact_length":
        return c**0.17 * np.exp(-c)
    if name == "z_g":
        return np.exp(-0.5 * ((c - 4.0) / 0.8) ** 2) * (c >= 3)
    if name == "z_v":
        return np.exp(-(c - 3.0) / 1.5) * (c >= 3)
    if name == "alpha_e":
        p = 0.3 + c
        for t in (0.473803, 0.454530, 0.433013, 0.406116, 0.378775):
            p = p + 2.0 * np.exp(-0.5 * ((c - t) / 0.002) ** 2)
        return p
    if name == "alpha_v":
        p = np.exp(-c)
        for t in (0.433013, 0.338430, 0.270553, 0.220925):
            p = p + 3.0 * np.exp(-0.5 * ((c - t) / 0.003) ** 2)
        return p
    if name == "fictitious_length":
        return 1.0 / np.sqrt(c + 1e-3) * np.exp(-c)
    if name in ("radial_grains", "radial_contacts"):
        return c * (c > 1.0) * (1 + 0.3 * np.cos(2 * np.pi * c) * np.exp(-c / 3))
    raise KeyError(name)


@dataclass
class SyntheticCampaign:
    N: tuple = (64, 128)
    E: tuple = tuple(10.0 ** -np.arange(3, 16, 2))
    seeds: int = 8
    variants: tuple = ("default",)
    truth: Truth = field(default_factory=Truth)
    histograms: tuple = tuple(DEFAULT_EDGES)
    hist_scale: float = 0.05     # expected counts per bin per disk (keeps files small)
    seed: int = 0
    variant_truth: dict = field(default_factory=dict)    # variant -> Truth (default: truth)
    variant_system: dict = field(default_factory=dict)   # variant -> extra system overrides

    def truth_of(self, variant):
        return self.variant_truth.get(variant, self.truth)

    def spec_yaml(self):
        """SPEC_YAML; with per-variant truths or systems, also the variants and their
        system overrides."""
        if not self.variant_truth and not self.variant_system:
            return SPEC_YAML
        text = SPEC_YAML.replace("exponent: 2.0", f"exponent: {float(self.truth.alpha)!r}")
        items = []
        for v in self.variants:
            if v == "default":
                continue
            system = dict(self.variant_system.get(v, {}))
            if self.truth_of(v).alpha != self.truth.alpha:
                system["potential"] = {"exponent": float(self.truth_of(v).alpha)}
            items.append({"name": v, **({"system": system} if system else {})})
        return text + "variants: " + json.dumps(items) + "\n"

    @property
    def n_tasks(self):
        return len(self.variants) * len(self.N) * len(self.E) * self.seeds


def task_table(c: SyntheticCampaign):
    """Canonical order: variant, N, E, seed index."""
    v, n, e, s = np.meshgrid(np.arange(len(c.variants)), np.asarray(c.N), np.asarray(c.E),
                             np.arange(c.seeds), indexing="ij")
    return (np.asarray(c.variants, dtype=object)[v.ravel()], n.ravel().astype(np.int64),
            e.ravel().astype(np.float64), s.ravel().astype(np.int64))


def scalars_for(c: SyntheticCampaign, variant, N, E, rng):
    T = len(N)
    N = N.astype(float)
    E_G = E * (1.0 + 0.1 * rng.random(T))
    vshift = np.array([0.01 * c.variants.index(x) for x in variant])
    noise_A = rng.normal(0, 1, T)
    noise_P = rng.normal(0, 1, T)
    noise_Z = rng.normal(0, 1, T)
    A_G, psi, dZ = np.empty(T), np.empty(T), np.empty(T)
    variant = np.asarray(variant, dtype=object)
    for v in dict.fromkeys(variant):  # the laws, variant by variant
        m = variant == v
        t = c.truth_of(v)
        n, e = N[m], E_G[m]
        sup = t.suppression(n, e)
        A_G[m] = (t.A_star(n) + vshift[m]
                  + t.c_A * e**t.beta_A * (1 + t.k_A * e**t.omega_A) * sup ** t.beta_Z
                  + noise_A[m] * t.sigma_A / np.sqrt(n))
        psi[m] = (t.P_star(n) + t.c_P * e**t.beta_P * sup ** (t.beta_P / t.z_power)
                  + noise_P[m] * t.sigma_P / np.sqrt(n))
        dZ[m] = np.where(e < t.iso_E, 0.0, t.c_Z * e**t.z_power * sup * (1 + t.sigma_Z * noise_Z[m]))
    N_R = rng.binomial(N.astype(np.int64), [c.truth_of(v).f_R for v in variant])
    phi = np.empty(T)
    for v in dict.fromkeys(variant):
        m = variant == v
        t = c.truth_of(v)
        phi[m] = t.phi_inf + t.phi_N / N[m] + t.c_phi * E_G[m] ** (1.0 / t.alpha)
        if t.sigma_phi > 0:  # drawn last: the other scalars stay as they were without it
            phi[m] += rng.normal(0, 1, int(m.sum())) * t.sigma_phi / np.sqrt(N[m])
    N_G = N - N_R
    z_iso = 4.0 - 2.0 / N_G
    z = z_iso + dZ
    N_C = np.round(z * N_G)
    N_V = N_C / 2 - N_G
    N_F = 2 * N_G - N_V
    return {
        "N": N, "N_G": N_G, "N_R": N_R.astype(float), "E_G": E_G,
        "phi": phi, "pressure": np.sqrt(E_G), "A_G": A_G, "A_V": 1.0 - A_G,
        "N_C": N_C, "N_V": N_V, "N_F": N_F, "z_g_mean": z, "z_iso": z_iso, "delta_Z": dZ,
        "psi_O": psi, "psi_DO": N_F / N_V, "identities_ok": np.ones(T),
        "jam_status": np.zeros(T), "force_residual": 1e-7 * rng.random(T), "iterations": rng.integers(5, 40, T).astype(float),
        "force_evaluations": rng.integers(1000, 9000, T).astype(float),
        "jam_seconds": rng.random(T), "analyze_seconds": 0.1 * rng.random(T),
    }


def write_store(path, c: SyntheticCampaign | None = None, *, status=None, block=4096):
    """Write the campaign file. ``status``: optional (T,) int8 (default all done).

    Returns the per-row data that was generated (dict), for checks.
    """
    rows = None
    c = c or SyntheticCampaign()
    variant, N, E, seed = task_table(c)
    T_full = len(N)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(c.seed)))
    sc = scalars_for(c, list(variant), N, E, rng)
    ids = np.array([f"{i:032x}".encode() for i in range(T_full)], dtype="S32")
    st = np.ones(T_full, np.int8) if status is None else np.asarray(status, np.int8).copy()
    sel = np.arange(T_full) if rows is None else np.asarray(rows)
    T = len(sel)
    with h5py.File(path, "w") as f:
        f.attrs.update(schema="jamming-campaign/1", format_version=2, name="synthetic",
                       spec_yaml=c.spec_yaml(),
                       spec_hash="0" * 32, package_version="0", git_commit="unknown",
                       versions=json.dumps({}), runs=json.dumps([]))
        g = f.create_group("tasks")
        g["id"] = ids[sel]
        g.create_dataset("variant", data=np.array(list(variant[sel]), dtype=object),
                         dtype=h5py.string_dtype())
        g["N"] = N[sel]
        g["E"] = E[sel]
        g["seed"] = seed[sel]
        g["attempts"] = np.ones(T, np.int32)
        g["wall"] = np.ones(T)
        g["rank"] = np.ones(T, np.int32)
        g.create_dataset("host", data=np.array(["synthetic"] * T, dtype=object),
                         dtype=h5py.string_dtype())
        err = np.array(["" if s != 2 else "RuntimeError: synthetic failure" for s in st[sel]],
                       dtype=object)
        g.create_dataset("error", data=err, dtype=h5py.string_dtype())
        done = st[sel] == 1
        s_grp = f.create_group("scalars")
        for k, v in sc.items():
            s_grp[k] = np.where(done, v[sel], np.nan)
        h_grp = f.create_group("histograms")
        for name in c.histograms:
            edges = DEFAULT_EDGES[name]
            lam = _shape(name, edges)
            lam = lam / lam.sum() * (edges.size - 1) * c.hist_scale
            hg = h_grp.create_group(name)
            hg["edges"] = edges
            ds = hg.create_dataset("counts", shape=(T, edges.size - 1), dtype=np.int64)
            for s in range(0, T, block):
                rows_b = sel[s:s + block]
                mult = (N[rows_b] / 64.0)[:, None]
                counts = rng.poisson(lam[None, :] * mult)
                counts[~done[s:s + block]] = 0
                ds[s:s + len(rows_b)] = counts
        g["status"] = st[sel]  # written last: the commit marker
    out = {k: v for k, v in sc.items()}
    out.update(variant=variant, N_label=N, E_target=E, seed_index=seed, status=st, id=ids)
    return out


def split_store(src, dsts):
    """Copy the rows of ``src`` round-robin into the files ``dsts`` (same layout)."""
    with h5py.File(src, "r") as f:
        T = f["tasks/status"].shape[0]
        for j, dst in enumerate(dsts):
            sel = np.arange(j, T, len(dsts))
            with h5py.File(dst, "w") as g:
                for k, v in f.attrs.items():
                    g.attrs[k] = v

                def copy(name, obj):
                    if isinstance(obj, h5py.Dataset):
                        data = obj[...]
                        if name.endswith("/edges"):
                            g.create_dataset(name, data=data)
                        else:
                            g.create_dataset(name, data=data[sel], dtype=obj.dtype)
                f.visititems(copy)
