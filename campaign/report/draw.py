"""Pictures of one packing: disks, contact network, grain and void polygons (matplotlib).

``scene(positions, radii, box, ...) -> Scene`` computes what a picture shows, in box
coordinates, without matplotlib: every primitive once (its *primary* copy, unwrapped
from one grain whose centre lies in the box) and its periodic images that reach into
the window. ``render(scene, ...) -> Figure`` draws it the way the paper's Figures 1
and 2 do; ``read_source(path, ...)`` reads a configuration file or one packing of a
campaign store; ``gallery(path, out)`` draws one packing of a store at three energies.

What is drawn (``LAYERS``), from the network of ``kernels.network.network`` and the
per-void Delaunay triangulation of ``kernels.triangulate``:

* ``disks``: every disk, coloured by species; rattlers (``network()['rattler']``) in
  their own colour, above the polygons (they lie inside void polygons);
* ``contacts``: one point per contact of the network, ``r_g + sigma_g/(sigma_g +
  sigma_g') r_gg'`` (N_C / 2 points);
* ``network``: one segment per contact, centre to centre (N_C / 2);
* ``grains``: one polygon per grain, its contact points counter-clockwise (N_G);
* ``voids``: one polygon per void, the contact points around its face (N_V);
* ``fictitious``: the z_v - 3 Delaunay chords of each void's cycle of centres (N_F);
* ``forces``: the network's segments again, as line widths proportional to the pair
  force ``(1 - r/s)^(alpha - 1) / s`` (``kernels.potential.pair_potential``).

Only contractible faces are drawn as voids (a face winding around the torus exists
only in a packing that fails its identities).

A tilted cell (box ``[Lx, Ly, xy]``, ``cell: shear``) is drawn as its parallelogram, spanned by
``(Lx, 0)`` and ``(xy Ly, Ly)``: the disks' centres are brought into it, periodic images are its
translates by those lattice vectors, and the default window (and what ``--region`` is checked
against) is the parallelogram's bounding box. A rectangular box is the case ``xy = 0``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.results.finished import variant_systems
from campaign.storage.configio import describe_box, detect_format, read_configuration, tilt
from campaign.storage.layout import SCHEMA
from campaign.storage.reader import open_store, read_summary

LAYERS = ("disks", "contacts", "network", "grains", "voids", "fictitious", "forces")
DEFAULT_LAYERS = ("disks", "contacts", "network", "grains", "voids", "fictitious")
FORMATS = (".png", ".svg", ".pdf")

#: How far a window (``--region``) may reach beyond the box, in box lengths.
REGION_LIMIT = 1.0

# Colours after the paper's Figures 1 and 2: contact points and fictitious contacts red,
# the network black, rattlers yellow, grain polygons blue, void polygons white.
SPECIES_COLOURS = ("#9fd39a", "#d5edcf", "#7fb3a8", "#c9dca2", "#a5c8e4")
RATTLER_COLOUR = "#f4d03f"
GRAIN_COLOUR = "#3d7bd9"
VOID_COLOUR = "#ffffff"
CONTACT_COLOUR = "#d62728"
FICTITIOUS_COLOUR = "#d62728"
NETWORK_COLOUR = "black"
FORCE_COLOUR = "#6d3a0f"
BOX_COLOUR = "#8e24aa"
#: The largest force is drawn this many mean disk diameters wide.
FORCE_WIDTH = 0.22


@dataclass
class Primitives:
    """Polygons (``verts`` (V, 2) with CSR ``ptr``), segments ((m, 2, 2)) or disks
    (``centres`` (m, 2), ``radii``, ``kind``): primary copies, then their images."""

    primary: dict
    images: dict = field(default_factory=dict)


@dataclass
class Scene:
    box: np.ndarray
    window: tuple  # (x0, y0, x1, y1)
    layers: tuple
    disks: Primitives
    contacts: Primitives
    network: Primitives
    grains: Primitives
    voids: Primitives
    fictitious: Primitives
    forces: np.ndarray  # (N_C/2,) pair force per network segment, in segment order
    species_labels: tuple  # label per disk kind >= 0
    counts: dict  # N, N_G, N_R, contacts, N_V, N_F of what is drawn (primaries)


# ----------------------------------------------------------------------------- geometry


def cell_bounds(box):
    """The cell's bounding box ``(x0, y0, x1, y1)``: ``(0, 0, Lx, Ly)`` for a rectangle, else the
    parallelogram's, with corners 0, ``(Lx, 0)``, ``(xy Ly, Ly)`` and their sum."""
    Lx, Ly = float(box[0]), float(box[1])
    if len(box) < 3:
        return (0.0, 0.0, Lx, Ly)
    t = tilt(box) * Ly
    return (min(0.0, t), 0.0, Lx + max(0.0, t), Ly)


def check_window(region, box):
    """The drawing window ``(x0, y0, x1, y1)`` from ``--region X Y W H`` (None: the cell's bounding
    box, ``cell_bounds``), which it must overlap and reach at most ``REGION_LIMIT`` of its sides
    beyond."""
    bx0, by0, bx1, by1 = cell_bounds(box)
    if region is None:
        return (bx0, by0, bx1, by1)
    x, y, w, h = (float(v) for v in region)
    if not all(math.isfinite(v) for v in (x, y, w, h)):
        raise UserError(f"--region: expected four finite numbers X Y W H, got {region}")
    if w <= 0 or h <= 0:
        raise UserError(f"--region: expected a positive width and height, got W = {w:g}, H = {h:g}")
    x1, y1 = x + w, y + h
    what = "the box" if len(box) < 3 else f"the tilted cell's bounding box (xy = {tilt(box):g})"
    if x >= bx1 or y >= by1 or x1 <= bx0 or y1 <= by0:
        raise UserError(f"--region {x:g} {y:g} {w:g} {h:g} lies outside {what} [{bx0:g}, {bx1:g}] x "
                        f"[{by0:g}, {by1:g}] (expected a window that overlaps it)")
    lim, W, H = REGION_LIMIT, bx1 - bx0, by1 - by0
    if x < bx0 - lim * W or y < by0 - lim * H or x1 > bx1 + lim * W or y1 > by1 + lim * H:
        raise UserError(f"--region {x:g} {y:g} {w:g} {h:g} reaches more than one box length beyond {what} "
                        f"[{bx0:g}, {bx1:g}] x [{by0:g}, {by1:g}] (periodic images fill at most one box "
                        "around it)")
    return (x, y, x1, y1)


def _bbox(kind, d):
    """Per-primitive bounding boxes (lo (m, 2), hi (m, 2))."""
    if kind == "poly":
        v, ptr = d["verts"], d["ptr"]
        if ptr.shape[0] <= 1:
            return np.empty((0, 2)), np.empty((0, 2))
        starts = ptr[:-1]
        return np.minimum.reduceat(v, starts, axis=0), np.maximum.reduceat(v, starts, axis=0)
    if kind == "seg":
        s = d["segments"]
        return s.min(axis=1), s.max(axis=1)
    if kind == "disk":
        r = d["radii"][:, None]
        return d["centres"] - r, d["centres"] + r
    p = d["points"]
    return p, p


def _select(kind, d, keep, shift):
    """The primitives ``keep`` of ``d`` translated by ``shift``."""
    if kind == "poly":
        ptr = d["ptr"]
        sizes = np.diff(ptr)[keep]
        starts = ptr[:-1][keep]
        idx = np.repeat(starts - np.concatenate(([0], np.cumsum(sizes)[:-1])), sizes) + np.arange(sizes.sum())
        return {"verts": d["verts"][idx] + shift, "ptr": np.concatenate(([0], np.cumsum(sizes)))}
    if kind == "seg":
        return {"segments": d["segments"][keep] + shift, "index": np.flatnonzero(keep)}
    if kind == "disk":
        return {"centres": d["centres"][keep] + shift, "radii": d["radii"][keep], "kind": d["kind"][keep]}
    return {"points": d["points"][keep] + shift}


def _concat(kind, parts):
    if not parts:
        return None
    if kind == "poly":
        verts = np.concatenate([p["verts"] for p in parts])
        sizes = np.concatenate([np.diff(p["ptr"]) for p in parts])
        return {"verts": verts, "ptr": np.concatenate(([0], np.cumsum(sizes)))}
    keys = parts[0].keys()
    return {k: np.concatenate([p[k] for p in parts]) for k in keys}


def _with_images(kind, primary, box, window):
    """Primary copies plus every translate by the cell's lattice vectors ``i (Lx, 0) + j (xy Ly,
    Ly)`` (whole box lengths in a rectangle, ``xy = 0``) that meets the window, in order of
    ``(i, j)``."""
    lo, hi = _bbox(kind, primary)
    if not lo.size:
        return Primitives(primary, {})
    Lx, Ly = float(box[0]), float(box[1])
    t = tilt(box) * Ly  # the x shift of one period along b
    x0, y0, x1, y1 = window
    # shifts i Lx + j t with x0 < hi + i Lx + j t and lo + i Lx + j t < x1 (likewise j Ly in y)
    jmin = np.ceil((y0 - hi[:, 1]) / Ly).astype(np.int64)
    jmax = np.floor((y1 - lo[:, 1]) / Ly).astype(np.int64)
    shifts = []
    for j in range(int(jmin.min()), int(jmax.max()) + 1):
        imin = np.ceil((x0 - hi[:, 0] - j * t) / Lx).astype(np.int64)
        imax = np.floor((x1 - lo[:, 0] - j * t) / Lx).astype(np.int64)
        shifts += [(i, j, imin, imax) for i in range(int(imin.min()), int(imax.max()) + 1) if (i, j) != (0, 0)]
    parts = []
    for i, j, imin, imax in sorted(shifts, key=lambda sh: sh[:2]):
        keep = (imin <= i) & (i <= imax) & (jmin <= j) & (j <= jmax)
        if keep.any():
            parts.append(_select(kind, primary, keep, np.array([i * Lx + j * t, j * Ly])))
    return Primitives(primary, _concat(kind, parts) or {})


def _into_cell(positions, box):
    """Centres moved by whole lattice vectors into the cell ``[0, 1)^2`` of fractional
    coordinates: ``[0, Lx) x [0, Ly)`` for a rectangle, the parallelogram of a tilted cell."""
    Lx, Ly, xy = float(box[0]), float(box[1]), tilt(box)
    p = np.array(positions, dtype=np.float64)
    k = np.floor(p[:, 1] / Ly)
    p[:, 1] -= k * Ly
    p[:, 0] -= k * xy * Ly
    p[:, 0] -= np.floor((p[:, 0] - xy * p[:, 1]) / Lx) * Lx
    # floor can leave a tiny negative input on the upper edge: fold it back
    up = p[:, 1] >= Ly
    p[up, 1] -= Ly
    p[up, 0] -= xy * Ly
    p[p[:, 0] - xy * p[:, 1] >= Lx, 0] -= Lx
    return p


def scene(positions, radii, box, species=None, *, exponent=2.0, region=None, layers=DEFAULT_LAYERS) -> Scene:
    """Everything a picture of this configuration shows (see the module docstring)."""
    from kernels.network import network
    from kernels.potential import pair_potential
    from kernels.triangulate import triangulate_polygon

    box = np.asarray(box, dtype=np.float64)
    window = check_window(region, box)
    pos = np.asarray(positions, dtype=np.float64)
    rad = np.asarray(radii, dtype=np.float64)
    pos = _into_cell(pos, box)  # everything else is unwrapped from the centres
    net = network(pos, rad, box)
    rattler = net["rattler"]
    offsets, src, dst = net["offsets"], net["src"], net["dst"]
    hd = np.stack([net["hdx"], net["hdy"]], axis=1)
    frac = net["frac"]
    twin = net["twin"]

    # disks: kind = species index (largest radius first when no species), -1 for rattlers
    if species is None:
        scales, inverse = np.unique(-rad, return_inverse=True)
        kind = inverse.astype(np.int64)
        labels = tuple(f"radius {-s:.3g}" for s in scales) if scales.size <= len(SPECIES_COLOURS) else ()
        if not labels:
            kind = np.zeros(rad.shape[0], np.int64)
            labels = ("disk",)
    else:
        kind = np.asarray(species, dtype=np.int64).copy()
        labels = tuple(f"species {chr(65 + k) if k < 26 else k} (radius {np.max(rad[kind == k], initial=0):.3g})"
                       for k in range(int(kind.max()) + 1))
    kind[rattler] = -1
    disks = {"centres": pos, "radii": rad, "kind": kind}

    # contacts: half-edges p < twin[p], one per contact
    one = np.flatnonzero(np.arange(src.shape[0]) < twin)
    centre = pos[src]
    cpoints = centre + frac[:, None] * hd
    contacts = {"points": cpoints[one]}
    segments = np.stack([centre[one], centre[one] + hd[one]], axis=1)
    r = np.hypot(hd[one, 0], hd[one, 1])
    s = rad[src[one]] + rad[dst[one]]
    _, force = pair_potential(r, s, exponent)
    netw = {"segments": segments}

    # grain polygons: each grain's contact points in counter-clockwise order
    sizes = np.diff(offsets)
    grains = {"verts": cpoints, "ptr": np.concatenate(([0], np.cumsum(sizes[sizes > 0])))}

    # voids: walk each face from its first grain, unwrapping with the displacements
    fptr, fhe = net["face_ptr"], net["face_he"]
    nf = fptr.shape[0] - 1
    Lmin = float(box[:2].min())
    contractible = np.hypot(net["sum_dx"], net["sum_dy"]) < 0.25 * Lmin
    d = hd[fhe]
    face = np.repeat(np.arange(nf), np.diff(fptr))
    before = np.cumsum(d, axis=0) - d
    before -= before[fptr[:-1]][face]
    vcentres = pos[src[fhe[fptr[:-1]]]][face] + before
    vverts = vcentres + frac[fhe][:, None] * d
    okf = contractible[face]
    vsizes = np.diff(fptr)[contractible]
    voids = {"verts": vverts[okf], "ptr": np.concatenate(([0], np.cumsum(vsizes)))}

    # fictitious contacts: the Delaunay chords of each void's cycle of centres
    chords = []
    for f in np.flatnonzero(contractible & (np.diff(fptr) >= 4)):
        c = vcentres[fptr[f]:fptr[f + 1]]
        ci, cj = triangulate_polygon(c)
        chords.append(np.stack([c[ci], c[cj]], axis=1))
    fict = {"segments": np.concatenate(chords) if chords else np.empty((0, 2, 2))}

    b = tuple(float(x) for x in box)
    n_g = int(np.count_nonzero(~rattler))
    counts = {"N": int(rad.shape[0]), "N_G": n_g, "N_R": int(rattler.sum()), "contacts": int(one.size),
              "N_V": int(contractible.sum()), "N_F": int(fict["segments"].shape[0]),
              "faces_not_drawn": int(nf - contractible.sum())}
    return Scene(
        box=box, window=window, layers=tuple(layers),
        disks=_with_images("disk", disks, b, window),
        contacts=_with_images("point", contacts, b, window),
        network=_with_images("seg", netw, b, window),
        grains=_with_images("poly", grains, b, window),
        voids=_with_images("poly", voids, b, window),
        fictitious=_with_images("seg", fict, b, window),
        forces=force, species_labels=labels, counts=counts,
    )


def check_layers(values):
    """``--layers`` values (names, comma- or space-separated, or 'all') -> tuple of names."""
    names = [s.strip() for v in values for s in v.split(",") if s.strip()]
    if names == ["all"]:
        return LAYERS
    unknown = [s for s in names if s not in LAYERS]
    if unknown or not names:
        raise UserError(f"--layers: unknown layer(s) {', '.join(unknown) or '(none given)'}; "
                        f"expected some of {', '.join(LAYERS)} or 'all'")
    return tuple(dict.fromkeys(names))


# ----------------------------------------------------------------------------- drawing


def _poly_list(d):
    if not d or d["ptr"].shape[0] <= 1:
        return []
    return np.split(d["verts"], d["ptr"][1:-1])


def render(sc: Scene, *, title=None, ax=None, legend=True, scale=True, size=None):
    """Draw the scene on ``ax`` (a new figure when None); returns the figure.

    Every artist carries a ``gid``: ``<layer>`` for the primary copies and
    ``<layer>-images`` for the periodic images (``disks`` also ``rattlers``), so that
    the figure's content can be counted.
    """
    from matplotlib.collections import EllipseCollection, LineCollection, PolyCollection

    from campaign.report.plots import _plt

    plt = _plt()
    x0, y0, x1, y1 = sc.window
    ww, wh = x1 - x0, y1 - y0
    Lx, Ly = float(sc.box[0]), float(sc.box[1])
    n_win = sc.counts["N"] * (ww * wh) / (Lx * Ly)
    if ax is None:
        width = size or float(np.clip(3.0 + 0.11 * math.sqrt(n_win), 5.0, 20.0))
        fig, ax = plt.subplots(figsize=(width, width * wh / ww + (1.0 if legend else 0.4)),
                               layout="constrained")
    else:
        fig = ax.figure
        width = fig.get_size_inches()[0] * ax.get_position().width
    ax.set_aspect("equal")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    # lengths in points: one box unit is this many points on the page
    unit = 72.0 * width / ww
    mean_d = 2.0 * float(np.mean(sc.disks.primary["radii"]))
    d_pt = unit * mean_d
    lw_net = float(np.clip(0.06 * d_pt, 0.15, 1.2))
    lw_edge = float(np.clip(0.03 * d_pt, 0.1, 0.6))
    layers = sc.layers
    handles = []
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    def disks(d, gid, rattlers):
        if not d:
            return
        sel = (d["kind"] < 0) if rattlers else (d["kind"] >= 0)
        if not sel.any():
            return
        colours = [RATTLER_COLOUR if k < 0 else SPECIES_COLOURS[k % len(SPECIES_COLOURS)] for k in d["kind"][sel]]
        w = 2.0 * d["radii"][sel]
        col = EllipseCollection(w, w, np.zeros(w.shape), units="xy", offsets=d["centres"][sel],
                                offset_transform=ax.transData, facecolors=colours, edgecolors="0.35",
                                linewidths=lw_edge, zorder=4.5 if rattlers else 1)
        col.set_gid(gid)
        ax.add_collection(col)

    if "disks" in layers:
        for d, suffix in ((sc.disks.primary, ""), (sc.disks.images, "-images")):
            disks(d, "disks" + suffix, False)
            disks(d, "rattlers" + suffix, True)
        for k, lab in enumerate(sc.species_labels):
            handles.append(Patch(facecolor=SPECIES_COLOURS[k % len(SPECIES_COLOURS)], edgecolor="0.35", label=lab))
        handles.append(Patch(facecolor=RATTLER_COLOUR, edgecolor="0.35", label=f"rattler ({sc.counts['N_R']})"))

    def polys(prims, gid, face, alpha, z, label):
        for d, suffix in ((prims.primary, ""), (prims.images, "-images")):
            col = PolyCollection(_poly_list(d), facecolors=face, edgecolors="#1f3f7a", linewidths=lw_edge,
                                 alpha=alpha, zorder=z)
            col.set_gid(gid + suffix)
            ax.add_collection(col)
        handles.append(Patch(facecolor=face, edgecolor="#1f3f7a", alpha=alpha, label=label))

    if "voids" in layers:
        polys(sc.voids, "voids", VOID_COLOUR, 0.55, 2, f"void polygon ({sc.counts['N_V']})")
    if "grains" in layers:
        polys(sc.grains, "grains", GRAIN_COLOUR, 0.45, 3, f"grain polygon ({sc.counts['N_G']})")

    def lines(prims, gid, colour, widths, style, z):
        for d, suffix in ((prims.primary, ""), (prims.images, "-images")):
            segs = d["segments"] if d else np.empty((0, 2, 2))
            lw = widths
            if not np.isscalar(widths) and suffix:  # an image has its primary's width
                lw = widths[d["index"]] if d else widths[:0]
            col = LineCollection(segs, colors=colour, linewidths=lw, linestyles=style, zorder=z,
                                 capstyle="round")
            col.set_gid(gid + suffix)
            ax.add_collection(col)

    if "network" in layers:
        lines(sc.network, "network", NETWORK_COLOUR, lw_net, "solid", 5)
        handles.append(Line2D([], [], color=NETWORK_COLOUR, lw=lw_net,
                              label=f"contact network ({sc.counts['contacts']} contacts)"))
    if "forces" in layers:
        f = sc.forces
        fmax = float(f.max()) if f.size and f.max() > 0 else 1.0
        widths = FORCE_WIDTH * d_pt * f / fmax
        lines(sc.network, "forces", FORCE_COLOUR, widths, "solid", 5.2)
        handles.append(Line2D([], [], color=FORCE_COLOUR, lw=min(FORCE_WIDTH * d_pt * 0.5, 4.0),
                              label=f"contact force (width; max {fmax:.3g})"))
    if "fictitious" in layers:
        lines(sc.fictitious, "fictitious", FICTITIOUS_COLOUR, lw_net, (0, (3, 2)), 5.5)
        handles.append(Line2D([], [], color=FICTITIOUS_COLOUR, lw=lw_net, ls="--",
                              label=f"fictitious contact ({sc.counts['N_F']})"))
    if "contacts" in layers:
        ms = float(np.clip(0.16 * d_pt, 0.8, 6.0))
        for d, suffix in ((sc.contacts.primary, ""), (sc.contacts.images, "-images")):
            pts = d.get("points", np.empty((0, 2))) if d else np.empty((0, 2))
            col = ax.scatter(pts[:, 0], pts[:, 1], s=ms * ms, c=CONTACT_COLOUR, linewidths=0, zorder=6)
            col.set_gid("contacts" + suffix)
        handles.append(Line2D([], [], color=CONTACT_COLOUR, marker="o", ls="", ms=4, label="contact point"))

    # the box's edges, where images begin
    if len(sc.box) > 2:  # a tilted cell: its parallelogram
        t = tilt(sc.box) * Ly
        ax.add_patch(plt.Polygon([(0, 0), (Lx, 0), (Lx + t, Ly), (t, Ly)], closed=True, fill=False, ec=BOX_COLOUR,
                                 lw=1.4, ls=(0, (6, 3)), zorder=7, gid="box"))
    else:
        ax.add_patch(plt.Rectangle((0, 0), Lx, Ly, fill=False, ec=BOX_COLOUR, lw=1.4, ls=(0, (6, 3)), zorder=7,
                                   gid="box"))
    edge = "cell edge (images beyond)" if len(sc.box) > 2 else "box edge (images beyond)"
    handles.append(Line2D([], [], color=BOX_COLOUR, lw=1.4, ls="--", label=edge))
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title)
    if scale:
        from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

        dmax = 2.0 * float(sc.disks.primary["radii"].max())
        bar = AnchoredSizeBar(ax.transData, dmax, f"{dmax:.3g} (largest diameter)", "lower left",
                              pad=0.3, sep=3, frameon=True, size_vertical=dmax * 0.06, fontproperties={"size": 8})
        bar.set_gid("scale")
        bar.set_zorder(8)
        bar.patch.set_alpha(0.8)
        ax.add_artist(bar)
    if legend and handles:
        fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)), fontsize=8,
                   frameon=False)
    return fig


# ----------------------------------------------------------------------------- sources


@dataclass
class Source:
    positions: np.ndarray
    radii: np.ndarray
    box: np.ndarray
    species: np.ndarray | None
    exponent: float
    label: str  # what the title says
    stem: str  # default output name


def _is_store(path):
    try:
        with open_store(path, accept="hdf5") as f:
            return f.attrs.get("schema") == SCHEMA and "tasks" in f
    except UserError:  # not one: read_configuration says what it is
        return False


def store_packings(path):
    """Rows of a campaign store that hold a configuration: (task table, rows, attrs)."""
    table = read_summary(path, configurations=True)
    have = table["configurations"]
    ids = np.array([i.decode() if isinstance(i, bytes) else str(i) for i in table["id"]])
    rows = np.flatnonzero([i in have for i in ids])
    return table, ids, rows


def read_source(path, *, task=None, index=None, fmt="auto", group="/", exponent=None, frame=None) -> Source:
    """The configuration to draw: a configuration file (``frame`` K of a GSD or extended XYZ
    file), or one packing of a campaign store."""
    path = str(path)
    if not os.path.exists(path):
        raise UserError(f"{path}: no such file (expected a configuration: text, .npz, HDF5, .gsd or extended XYZ, "
                        "or a campaign store)")
    kind = detect_format(path) if fmt == "auto" else fmt
    if kind == "hdf5" and not os.path.isdir(path) and _is_store(path):
        table, ids, rows = store_packings(path)
        if rows.size == 0:
            raise UserError(f"{path}: the campaign store holds no configurations (a spec keeps them with "
                            "'store: {configurations: true}'); draw a configuration file instead")
        if task is not None and index is not None:
            raise UserError("give --task or --index, not both")
        if frame is not None:
            raise UserError(f"--frame {frame}: picks a frame of a .gsd or extended XYZ file; in a campaign store "
                            "--task ID or --index ROW picks the packing")
        if task is not None:
            match = np.flatnonzero(np.char.startswith(ids.astype(str), task))
            if match.size == 0:
                raise UserError(f"{path}: no task with id {task!r} (ids are 32 hex characters; "
                                f"'campaign status {path}' lists the tasks)")
            if match.size > 1:
                raise UserError(f"{path}: {match.size} tasks have ids starting with {task!r}; give more characters")
            row = int(match[0])
        elif index is not None:
            if not 0 <= index < ids.size:
                raise UserError(f"--index {index}: expected a row of the task table, 0 to {ids.size - 1}")
            row = int(index)
        else:
            row = int(rows[0])
        if row not in set(rows.tolist()):
            status = int(table["status"][row])
            why = {0: "still pending", 2: "failed"}.get(status, "done, but its configuration was not kept")
            raise UserError(f"{path}: task row {row} (id {ids[row]}) has no stored configuration ({why}); "
                            f"rows with one: {', '.join(str(r) for r in rows[:8])}"
                            f"{' ...' if rows.size > 8 else ''}")
        conf = read_configuration(path, fmt="hdf5", group=f"/configurations/{ids[row]}")
        variant = table["variant"][row]
        variant = variant.decode() if isinstance(variant, bytes) else str(variant)
        N, E, seed = int(table["N"][row]), float(table["E"][row]), int(table["seed"][row])
        if exponent is None:  # the potential of the packing's own variant, which may override the spec's
            alpha = variant_systems(table["attrs"], [variant])[variant]["exponent"]
        else:
            alpha = exponent
        label = f"{Path(path).name}: row {row}, {variant}, N = {N}, E = {E:.3g}, seed {seed}"
        return Source(conf.positions, conf.radii, conf.box, conf.species, alpha, label,
                      f"{Path(path).stem}_{ids[row][:8]}")
    if task is not None or index is not None:
        raise UserError(f"{path}: --task and --index choose a packing of a campaign store; this is a "
                        "configuration file")
    conf = read_configuration(path, fmt=fmt, group=group, frame=frame)
    alpha = exponent if exponent is not None else (conf.exponent or 2.0)
    label, stem = Path(path).name, Path(path).stem
    if conf.frame is not None:
        info = conf.info or {}
        label += f": frame {conf.frame}"
        if all(k in info for k in ("variant", "N", "E", "seed")):
            label += f", {info['variant']}, N = {info['N']}, E = {float(info['E']):.3g}, seed {info['seed']}"
        if conf.n_frames != 1:
            stem += f"_{conf.frame}"
    return Source(conf.positions, conf.radii, conf.box, conf.species, alpha, label, stem)


def title_of(src: Source, sc: Scene) -> str:
    c = sc.counts
    x0, y0, x1, y1 = sc.window
    whole = sc.window == cell_bounds(sc.box)
    w = "" if whole else f"; window [{x0:.3g}, {x1:.3g}] x [{y0:.3g}, {y1:.3g}] of the box {describe_box(sc.box)}"
    return f"{src.label}\nN = {c['N']} disks, N_G = {c['N_G']} grains{w}"


def gallery(path, out, *, dpi=90):
    """One packing of a store at three energies (lowest, middle, highest stored) side by side.

    Picks the default variant's largest N whose seed has configurations at the most
    energies; returns the path written, or None when the store holds no configurations.
    """
    from kernels.analysis import analyze

    table, ids, rows = store_packings(path)
    if rows.size == 0:
        return None
    var = np.array([v.decode() if isinstance(v, bytes) else str(v) for v in table["variant"]])
    N, E, seed = table["N"], table["E"], table["seed"]
    pick = rows[var[rows] == "default"] if np.any(var[rows] == "default") else rows
    best = None
    for key in sorted({(int(N[r]), int(seed[r])) for r in pick}, key=lambda k: (-k[0], k[1])):
        cand = [r for r in pick if (int(N[r]), int(seed[r])) == key]
        if best is None or len(cand) > len(best):
            best = cand
    best = sorted(best, key=lambda r: E[r])
    chosen = [best[0], best[len(best) // 2], best[-1]] if len(best) >= 3 else best
    chosen = list(dict.fromkeys(chosen))
    from campaign.report.plots import _plt

    plt = _plt()
    fig, axes = plt.subplots(1, len(chosen), figsize=(3.6 * len(chosen), 4.2), layout="constrained",
                             squeeze=False)
    for ax, r in zip(axes[0], chosen):
        src = read_source(path, index=int(r))
        sc = scene(src.positions, src.radii, src.box, src.species, exponent=src.exponent)
        e_g = analyze(src.positions, src.radii, src.box, [], exponent=src.exponent).scalars["E_G"]
        render(sc, ax=ax, legend=False, scale=ax is axes[0][0],
               title=f"E = {E[r]:.0e}: E_G = {e_g:.3g}\nN_G = {sc.counts['N_G']}, contacts {sc.counts['contacts']}")
    fig.suptitle(f"{Path(path).name}: N = {int(N[chosen[0]])}, seed {int(seed[chosen[0]])}, "
                 f"variant {var[chosen[0]]}", fontsize=9)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out
