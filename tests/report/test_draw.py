"""`campaign draw`: the picture's content, counted through the figure's artists.

The counts of disks, rattlers, contact points, network segments, grain and void
polygons and fictitious contacts must equal the analysis' counts; the periodic images
must tile any window; the triangular crystal gives its analytic picture.
"""

import matplotlib
from helpers import clipped_area, polygon_area

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import kernels  # noqa: E402
from campaign import cli  # noqa: E402
from campaign.report import draw
from kernels.network import network  # noqa: E402


def _by_gid(fig):
    out = {}
    for ax in fig.axes:
        for c in ax.collections:
            out.setdefault(c.get_gid(), []).append(c)
    return out


def _n(arts, gid, what):
    cs = arts.get(gid, [])
    if what == "offsets":
        return sum(len(c.get_offsets()) for c in cs)
    if what == "paths":
        return sum(len(c.get_paths()) for c in cs)
    return sum(len(c.get_segments()) for c in cs)


@pytest.fixture(scope="module")
def packing32():
    p = kernels.jam(32, 1e-6, seed=3)
    return p


def test_counts_equal_the_analysis(packing32):
    p = packing32
    a = kernels.analyze(p.positions, p.radii, p.box, ["fictitious"])
    s = a.scalars
    assert a.ok
    sc = draw.scene(p.positions, p.radii, p.box, p.species, layers=draw.LAYERS)
    fig = draw.render(sc)
    arts = _by_gid(fig)
    n_rattlers = int(network(p.positions, p.radii, p.box)["rattler"].sum())
    assert n_rattlers == s["N_R"]
    assert _n(arts, "disks", "offsets") + _n(arts, "rattlers", "offsets") == s["N"] == 32
    assert _n(arts, "rattlers", "offsets") == s["N_R"]
    assert _n(arts, "contacts", "offsets") == s["N_C"] // 2
    assert _n(arts, "network", "segments") == s["N_C"] // 2
    assert _n(arts, "forces", "segments") == s["N_C"] // 2
    assert _n(arts, "grains", "paths") == s["N_G"]
    assert _n(arts, "voids", "paths") == s["N_V"]
    assert _n(arts, "fictitious", "segments") == s["N_F"] == 2 * s["N_G"] - s["N_V"]
    # every grain polygon has z_g vertices, every void polygon z_v
    z_g = sorted(len(c) for c in draw._poly_list(sc.grains.primary))
    assert z_g == sorted(a.z_g[~a.rattler].tolist())
    assert sorted(len(c) for c in draw._poly_list(sc.voids.primary)) == sorted(a.z_v.tolist())
    # the drawn polygons tile the box, in the analysis' proportion A_G : A_V
    ga = sum(polygon_area(v) for v in draw._poly_list(sc.grains.primary))
    va = sum(polygon_area(v) for v in draw._poly_list(sc.voids.primary))
    area = float(p.box[0] * p.box[1])
    assert ga + va == pytest.approx(area, rel=1e-12)
    assert ga / (ga + va) == pytest.approx(s["A_G"] / (s["A_G"] + s["A_V"]), rel=1e-12)
    # the widths are the harmonic pair forces (1 - r/s) / s of the network's contacts
    i, j = a.contacts[~a.rattler[a.contacts].any(axis=1)].T
    d = p.positions[j] - p.positions[i]
    d -= np.round(d / p.box) * p.box
    sig = p.radii[i] + p.radii[j]
    expected = (1 - np.hypot(d[:, 0], d[:, 1]) / sig) / sig
    assert np.allclose(np.sort(sc.forces), np.sort(expected), rtol=1e-9, atol=0)
    plt.close(fig)


def _triangular_crystal(nx=6, ny=4, a=0.1):
    xs, ys = np.meshgrid(np.arange(nx), np.arange(ny))
    x = a * (xs + 0.5 * (ys % 2))
    y = a * np.sqrt(3) / 2 * ys
    pos = np.stack([x.ravel(), y.ravel()], axis=1) + 0.013
    box = (nx * a, ny * a * np.sqrt(3) / 2)
    radii = np.full(nx * ny, 0.5 * a * (1 + 1e-6))  # a hair of overlap: every neighbour touches
    return pos, radii, box


def test_triangular_crystal_is_analytic():
    pos, radii, box = _triangular_crystal()
    n = pos.shape[0]
    sc = draw.scene(pos, radii, box)
    fig = draw.render(sc)
    arts = _by_gid(fig)
    assert _n(arts, "disks", "offsets") == n and _n(arts, "rattlers", "offsets") == 0
    assert _n(arts, "contacts", "offsets") == _n(arts, "network", "segments") == 3 * n
    assert _n(arts, "grains", "paths") == n
    assert _n(arts, "voids", "paths") == 2 * n
    assert _n(arts, "fictitious", "segments") == 0
    assert all(len(v) == 3 for v in draw._poly_list(sc.voids.primary))
    assert all(len(v) == 6 for v in draw._poly_list(sc.grains.primary))
    ga = sum(polygon_area(v) for v in draw._poly_list(sc.grains.primary))
    assert ga / (box[0] * box[1]) == pytest.approx(0.75, rel=1e-5)  # A_G = 3/4
    plt.close(fig)


@pytest.mark.parametrize("region", [None, (-0.3, 0.25, 1.5, 0.6), (0.5, -0.7, 0.4, 1.9), (0.9, 0.9, 0.9, 0.9)])
def test_periodic_images_tile_any_window(packing32, region):
    p = packing32
    sc = draw.scene(p.positions, p.radii, p.box, p.species, region=region)
    x0, y0, x1, y1 = sc.window
    polys = []
    for prims in (sc.grains, sc.voids):
        polys += draw._poly_list(prims.primary) + draw._poly_list(prims.images)
    covered = sum(clipped_area(v, x0, y0, x1, y1) for v in polys)
    assert covered == pytest.approx((x1 - x0) * (y1 - y0), rel=1e-9)
    # every image of a disk that reaches into the window is drawn, once (brute force over shifts)
    Lx, Ly = p.box
    expected = set()
    for i, (c, r) in enumerate(zip(np.mod(p.positions, p.box), p.radii)):
        for sx in range(-3, 4):
            for sy in range(-3, 4):
                cx, cy = c[0] + sx * Lx, c[1] + sy * Ly
                if cx + r > x0 and cx - r < x1 and cy + r > y0 and cy - r < y1:
                    expected.add((i, sx, sy))
    drawn = np.concatenate([sc.disks.primary["centres"], sc.disks.images["centres"]])
    assert len(drawn) == len(expected) + sum(1 for i in range(32) if (i, 0, 0) not in expected)
    # images of segments are translates of primaries by whole box lengths
    prim = sc.network.primary["segments"]
    img = sc.network.images.get("segments", np.empty((0, 2, 2)))
    shift = (img - prim[sc.network.images["index"]]) / p.box if img.size else np.zeros((0, 2, 2))
    assert np.allclose(shift, np.round(shift), atol=1e-9)


# ----------------------------------------------------------------------------- command line


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("stores")
    base = ("name: drawtest\nseed: 5\ngrid:\n  N_G: [16]\n  E_G: [1.0e-2, 1.0e-4, 1.0e-6]\n  seeds: 1\n"
            "observables: [scalars]\n")
    (d / "with.yaml").write_text(base + "store: {configurations: true}\n")
    (d / "without.yaml").write_text(base)
    for name in ("with", "without"):
        assert cli.main(["run", str(d / f"{name}.yaml"), "--out", str(d / f"{name}.h5"),
                         "--launcher", "inline", "--quiet"]) == 0
    return d


def test_draw_files_in_every_format(packing32, tmp_path, capsys):
    p = packing32
    src = tmp_path / "p.npz"
    np.savez(src, positions=p.positions, radii=p.radii, box=p.box, species=p.species)
    magic = {".png": b"\x89PNG", ".svg": b"<?xml", ".pdf": b"%PDF"}
    for suffix, head in magic.items():
        out = tmp_path / f"p{suffix}"
        assert cli.main(["draw", str(src), "--out", str(out), "--layers", "all"]) == 0
        assert out.read_bytes()[:len(head)] == head
    a = kernels.analyze(p.positions, p.radii, p.box).scalars
    err = capsys.readouterr().err
    assert f"{a['N_C'] // 2} contacts, {a['N_G']} grain polygons, {a['N_V']} void polygons" in err


def test_draw_a_store_by_task_and_row(stores, tmp_path):
    import h5py

    path = stores / "with.h5"
    with h5py.File(path, "r") as f:
        ids = [i.decode() for i in f["tasks/id"][:]]
    assert cli.main(["draw", str(path), "--index", "2", "--out", str(tmp_path / "a.png")]) == 0
    assert cli.main(["draw", str(path), "--task", ids[1][:10], "--out", str(tmp_path / "b.svg"),
                     "--region", "-0.2", "-0.2", "0.5", "0.5"]) == 0
    assert (tmp_path / "a.png").stat().st_size > 5000 and (tmp_path / "b.svg").stat().st_size > 5000
    src = draw.read_source(path, task=ids[1])
    with h5py.File(path, "r") as f:
        assert np.array_equal(src.positions, f[f"configurations/{ids[1]}/positions"][:])


@pytest.mark.slow
def test_plot_adds_the_gallery(stores, tmp_path, capsys):
    assert cli.main(["plot", str(stores / "with.h5"), "--out", str(tmp_path), "--boot", "0",
                     "--min-packings", "2"]) == 0
    assert (tmp_path / "packing_gallery.png").read_bytes()[:4] == b"\x89PNG"
    assert "packing_gallery.png" in capsys.readouterr().err
    assert cli.main(["plot", str(stores / "without.h5"), "--out", str(tmp_path / "n"), "--boot", "0",
                     "--min-packings", "2"]) == 0
    assert not (tmp_path / "n" / "packing_gallery.png").exists()


def test_bad_input_exits_2_with_a_message(stores, packing32, tmp_path, capsys):
    p = packing32
    src = tmp_path / "p.npz"
    np.savez(src, positions=p.positions, radii=p.radii, box=p.box)
    cases = [
        ([str(tmp_path / "missing.txt")], "no such file"),
        ([str(stores / "without.h5")], "holds no configurations"),
        ([str(stores / "with.h5"), "--task", "ffffffffff"], "no task with id"),
        ([str(stores / "with.h5"), "--index", "99"], "expected a row of the task table"),
        ([str(src), "--region", "1.5", "0", "0.2", "0.2"], "outside the box"),
        ([str(src), "--region", "-1.5", "0", "0.2", "0.2"], "outside the box"),
        ([str(src), "--region", "-1.2", "0", "1.5", "0.2"], "more than one box length"),
        ([str(src), "--region", "0", "0", "0", "0.2"], "positive width"),
        ([str(src), "--layers", "disks,voronoi"], "unknown layer(s) voronoi"),
        ([str(src), "--out", str(tmp_path / "p.jpg")], "expected a .png, .svg or .pdf"),
        ([str(src), "--task", "abc"], "choose a packing of a campaign store"),
        ([str(src), "--exponent", "1.5"], "--exponent"),
    ]
    for argv, message in cases:
        assert cli.main(["draw", *argv, "--out", str(tmp_path / "x.png")] if "--out" not in argv
                        else ["draw", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
    bad = tmp_path / "bad.txt"
    bad.write_text("1 1\n0.5 0.5 0.1\n0.2 nan 0.1\n")
    assert cli.main(["draw", str(bad)]) == 2
    assert "line 3" in capsys.readouterr().err


def test_a_configuration_without_network_draws_its_rattlers(tmp_path):
    """Tiny disks in a big box: no contact, every disk a rattler, nothing else to draw."""
    pos = np.array([[0.1, 0.1], [0.5, 0.5], [0.7, 0.2]])
    sc = draw.scene(pos, np.array([0.01, 0.01, 0.02]), (1.0, 1.0), layers=draw.LAYERS)
    assert sc.counts == {"N": 3, "N_G": 0, "N_R": 3, "contacts": 0, "N_V": 0, "N_F": 0, "faces_not_drawn": 0}
    arts = _by_gid(draw.render(sc))
    assert _n(arts, "rattlers", "offsets") == 3 and _n(arts, "disks", "offsets") == 0
    assert _n(arts, "grains", "paths") == _n(arts, "network", "segments") == 0
    plt.close("all")


def test_a_store_variant_is_drawn_with_its_own_potential(tmp_path):
    """A variant that overrides the system's potential (Hertz, alpha = 2.5) is drawn with its own
    exponent, not the spec's top-level one: the forces layer's widths are its pair forces and the
    packing's E_G computed with the drawn exponent is the one the store holds."""
    import h5py

    spec = tmp_path / "hertz.yaml"
    spec.write_text("name: hertzdraw\nseed: 7\ngrid:\n  N_G: [16]\n  E_G: [1.0e-4]\n  seeds: 1\n"
                    "variants:\n  - name: hertz\n    system: {potential: {exponent: 2.5}}\n"
                    "observables: [scalars]\nstore: {configurations: true}\n")
    out = tmp_path / "hertz.h5"
    assert cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--quiet"]) == 0
    with h5py.File(out, "r") as f:
        variant = f["tasks/variant"].asstr()[:]
        stored = f["scalars/E_G"][:]
    for name, alpha in (("default", 2.0), ("hertz", 2.5)):
        row = int(np.flatnonzero(variant == name)[0])
        src = draw.read_source(out, index=row)
        assert src.exponent == alpha, name
        a = kernels.analyze(src.positions, src.radii, src.box, [], exponent=src.exponent)
        assert a.scalars["E_G"] == pytest.approx(stored[row], rel=1e-12), name
        sc = draw.scene(src.positions, src.radii, src.box, src.species, exponent=src.exponent, layers=draw.LAYERS)
        i, j = a.contacts[~a.rattler[a.contacts].any(axis=1)].T
        d = src.positions[j] - src.positions[i]
        d -= np.round(d / src.box[:2]) * src.box[:2]
        sig = src.radii[i] + src.radii[j]
        expected = (1 - np.hypot(d[:, 0], d[:, 1]) / sig) ** (alpha - 1) / sig
        assert np.allclose(np.sort(sc.forces), np.sort(expected), rtol=1e-9, atol=0), name
