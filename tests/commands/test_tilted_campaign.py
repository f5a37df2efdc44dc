"""Campaigns in the shear-stabilised ensemble: the spec's ``cell``, the stored ``gamma``
and ``sigma_xy``, tilted configurations through every reader and writer, ``campaign draw`` of a
tilted cell, and a store written before these scalars.

Expectations are computed independently of the code under test: fractional coordinates by hand,
the exported files read with their own libraries (gsd, ASE), the store with plain h5py.
"""

import json
from pathlib import Path

import h5py
import matplotlib
from helpers import clipped_area, polygon_area

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from campaign import cli  # noqa: E402
from campaign.plan import tasks  # noqa: E402
from campaign.plan.parse import load_spec, parse_spec  # noqa: E402
from campaign.run.worker import SyntheticTask  # noqa: E402
from campaign.storage.configio import read_configuration  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "tests" / "data" / "config_packing32.txt"

MINIMAL = """\
name: t
seed: 7
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
"""


def _bits_equal(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def _frac(positions, box):
    """Fractional coordinates by hand: r = s_x (Lx, 0) + s_y (xy Ly, Ly)."""
    Lx, Ly, xy = (float(v) for v in box)
    p = np.asarray(positions, np.float64)
    sy = p[:, 1] / Ly
    return np.column_stack([(p[:, 0] - xy * Ly * sy) / Lx, sy])


def _sheared(xy=0.04, stretch=1.03):
    """The 32-disk example packing stretched (Lx = stretch, Ly = 1/stretch: the same area) and
    sheared by ``xy``: r -> (stretch x + xy y / stretch, y / stretch) in the cell [Lx, Ly, xy];
    centres folded back into [0, Lx) x [0, Ly) by the cell's lattice vectors."""
    rows = [line.split() for line in EXAMPLE.read_text().splitlines() if line and not line.startswith("#")]
    arr = np.array([[float(x) for x in r] for r in rows[1:]])
    Lx, Ly = stretch, 1.0 / stretch
    y = arr[:, 1] * Ly
    x = arr[:, 0] * Lx + xy * y
    x -= Lx * np.floor(x / Lx)
    return np.column_stack([x, y]), arr[:, 2].copy(), np.array([Lx, Ly, xy])


def _crystal(m=8, d=0.1):
    """A triangular crystal of m*m disks in its own rhombic cell: a = (m d, 0), b = m (d/2, d sqrt3/2),
    so xy = 1/sqrt3; a hair of overlap makes every neighbour touch."""
    Lx, Ly = m * d, m * d * np.sqrt(3) / 2
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    x = d * (i + 0.5 * j).ravel() + 0.013
    y = d * np.sqrt(3) / 2 * j.ravel() + 0.011
    x -= Lx * np.floor(x / Lx)
    return np.column_stack([x, y]), np.full(m * m, 0.5 * d * (1 + 1e-6)), np.array([Lx, Ly, 1 / np.sqrt(3)])


# ----------------------------------------------------------------------------- the spec


def test_cell_fixed_keeps_every_task_id_and_shear_is_part_of_the_identity():
    plain = parse_spec(MINIMAL)
    fixed = parse_spec(MINIMAL + "protocol: {cell: fixed}\n")
    shear = parse_spec(MINIMAL + "protocol: {cell: shear}\n")
    assert fixed.variants[0].protocol == plain.variants[0].protocol and fixed.hash == plain.hash
    assert shear.variants[0].protocol_dict == dict(plain.variants[0].protocol_dict, cell="shear")
    a, b, c = (tasks.expand(s) for s in (plain, fixed, shear))
    assert [t.id for t in a] == [t.id for t in b]
    assert not {t.id for t in a} & {t.id for t in c}
    # the same random starts: the seed words leave the protocol out
    assert [t.entropy for t in a] == [t.entropy for t in c]
    both = parse_spec(MINIMAL + "variants:\n  - {name: shear, cell: shear}\n")
    ids = [t.id for t in tasks.expand(both)]
    assert ids[:len(a)] == [t.id for t in a] and ids[len(a):] == [t.id for t in c]


@pytest.mark.parametrize("protocol, fragments", [
    ("{cell: sheared}", ["protocol.cell: unknown cell 'sheared'; expected one of fixed, shear"]),
    ("{cell: 1}", ["protocol.cell: expected one of fixed, shear"]),
    ("{cell: shear, minimizer: cg}", ["protocol.cell: cell 'shear'", "minimizer 'cg'"]),
    ("{cell: shear, endgame: newton}", ["protocol.cell: cell 'shear'", "endgame 'newton'"]),
    ("{cell: shear, endgame: auto}", ["protocol.cell: cell 'shear'", "endgame 'auto'"]),
    ("{cell: shear, route: pressure}", ["protocol.cell: cell 'shear'", "route 'pressure'"]),
    ("{cell: shear, minimizer: cg, stop: energy}", ["protocol.stop: stop 'energy'", "cell 'shear'"]),
])
def test_bad_cell_settings_exit_2(tmp_path, capsys, protocol, fragments):
    p = tmp_path / "s.yaml"
    p.write_text(MINIMAL + f"protocol: {protocol}\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"{p}:4: " in err
    for f in fragments:
        assert f in err, err
    if fragments[0].startswith("protocol.cell: cell"):
        assert "needs minimizer 'fire', stop 'force', route 'ohern' and endgame 'none'" in err


def test_a_variant_inheriting_shear_is_checked_too(capsys):
    from campaign.errors import UserError

    with pytest.raises(UserError, match=r"variants\[0\]\.cell: cell 'shear'.*endgame 'newton'"):
        parse_spec(MINIMAL + "protocol: {cell: shear}\nvariants:\n  - {name: n, endgame: newton}\n", "s.yaml")
    # a fixed-cell variant of a shear base may take the endgame
    s = parse_spec(MINIMAL + "protocol: {cell: shear}\nvariants:\n  - {name: n, cell: fixed, endgame: newton}\n")
    assert s.variants[1].protocol_dict == dict(endgame="newton", force_tolerance=1e-6, window=0.1)


def test_the_shear_campaign(capsys):
    from campaign.plan.tasks import warm_ups as _warm_ups

    spec = load_spec(ROOT / "campaigns" / "shear.yaml")
    assert [v.name for v in spec.variants] == ["default", "shear"]
    assert "cell" not in spec.variants[0].protocol_dict
    assert spec.variants[1].protocol_dict == dict(spec.variants[0].protocol_dict, cell="shear")
    assert spec.N == (64, 128, 256, 512, 1024) and spec.E[0] == 1e-14 and spec.E[-1] == 1e-3
    assert "moduli" in spec.observables and spec.configurations
    ts = tasks.expand(spec)
    fixed = [t for t in ts if t.variant == "default"]
    shear = [t for t in ts if t.variant == "shear"]
    assert [t.entropy for t in fixed] == [t.entropy for t in shear]  # the same random starts
    # the warm-up compiles both the fixed and the shear cell's search
    assert sorted(dict(p).get("cell", "fixed") for p in _warm_ups(ts)) == ["fixed", "shear"]
    assert cli.main(["validate", str(ROOT / "campaigns" / "shear.yaml")]) == 0
    out = capsys.readouterr().out
    assert "advice: 'shear'" not in out  # no Newton endgame for a shear-stabilised cell


class _FakeKernels:
    """Records what the worker hands to ``kernels.jam`` and ``kernels.analyze``."""

    def __init__(self):
        self.calls = []

    def jam(self, n, energy, seed, **kw):
        from types import SimpleNamespace

        self.calls.append(("jam", kw))
        box = np.array([1.0, 1.0, 0.01]) if kw.get("cell") == "shear" else np.array([1.0, 1.0])
        return SimpleNamespace(positions=np.zeros((n, 2)), radii=np.full(n, 0.01), box=box,
                               species=np.zeros(n, np.int32), force_residual=0.0, iterations=1,
                               force_evaluations=1, status_code=0, status="converged", energy_nonrattler=1.0,
                               pressure=2.0, phi=0.8, gamma=float(box[2]) if len(box) > 2 else 0.0, sigma_xy=-3e-9)

    def analyze(self, positions, radii, box, **kw):
        from types import SimpleNamespace

        self.calls.append(("analyze", kw))
        sc = {"N": len(radii), "z_iso": 4.0, "gamma": float(box[2]) if len(box) > 2 else 0.0, "sigma_xy": 5e-9}
        return SimpleNamespace(scalars=sc, identities={"euler": True}, histograms={})


@pytest.mark.parametrize("cell", ["fixed", "shear"])
def test_the_worker_passes_the_cell_to_jam_and_analyze(monkeypatch, cell):
    import kernels
    from campaign.run.worker import KernelTask

    spec = parse_spec(MINIMAL + f"protocol: {{cell: {cell}}}\nobservables: [scalars]\n")
    task = tasks.expand(spec)[0]
    system = spec.system.canonical()
    context = {"system": system, "observables": ["scalars"], "histograms": [], "edges": {}}
    fake = _FakeKernels()
    monkeypatch.setattr(kernels, "jam", fake.jam)
    monkeypatch.setattr(kernels, "analyze", fake.analyze)
    scalars, _, config = KernelTask().run(task.payload(), dict(context, configurations=True))
    (_, jam_kw), (_, an_kw) = fake.calls
    if cell == "shear":
        assert jam_kw["cell"] == "shear" and an_kw["cell"] == "shear"
        assert config["box"].shape == (3,) and scalars["gamma"] == 0.01
    else:  # the default reaches neither: the fixed cell's calls are those of before
        assert "cell" not in jam_kw and "cell" not in an_kw
        assert config["box"].shape == (2,) and scalars["gamma"] == 0.0
    assert scalars["sigma_xy"] == 5e-9  # the analysis' (over every contact)


# ----------------------------------------------------------------------------- configuration files


def test_a_tilted_box_round_trips_through_text_npz_and_hdf5(tmp_path):
    pos, rad, box = _sheared()
    text = tmp_path / "c.txt"
    text.write_text("# a sheared packing\n" + " ".join(repr(float(v)) for v in box) + "\n"
                    + "".join(f"{x!r} {y!r} {r!r}\n" for (x, y), r in zip(pos.tolist(), rad.tolist())))
    np.savez(tmp_path / "c.npz", positions=pos, radii=rad, box=box)
    with h5py.File(tmp_path / "c.h5", "w") as f:
        g = f.create_group("conf")
        g["positions"], g["radii"], g["box"] = pos, rad, box
    for path, kw in ((text, {}), (tmp_path / "c.npz", {}), (tmp_path / "c.h5", {"group": "/conf"})):
        c = read_configuration(path, **kw)
        assert _bits_equal(c.positions, pos) and _bits_equal(c.radii, rad) and _bits_equal(c.box, box), path
        assert c.cell is None and c.notes == ()
    # a tilt of exactly 0 is the rectangle
    np.savez(tmp_path / "z.npz", positions=pos, radii=rad, box=np.array([box[0], box[1], 0.0]))
    assert read_configuration(tmp_path / "z.npz").box.tolist() == box[:2].tolist()
    # a tilt beyond 1 is the same lattice with b - k a: reduced, with a note
    big = np.array([box[0], box[1], box[2] + 2 * box[0] / box[1]])
    np.savez(tmp_path / "big.npz", positions=pos, radii=rad, box=big)
    c = read_configuration(tmp_path / "big.npz")
    assert c.box[2] == pytest.approx(box[2], abs=1e-14) and "reduced" in c.notes[0]


def test_positions_are_checked_in_the_cells_fractional_coordinates(tmp_path, capsys):
    box = np.array([1.0, 1.0, 1.0])
    ok = np.array([[1.9, 0.95], [0.2, 0.1]])  # x beyond 1.9: inside the tilted cell's first image
    np.savez(tmp_path / "ok.npz", positions=ok, radii=np.full(2, 0.05), box=box)
    assert _frac(read_configuration(tmp_path / "ok.npz").positions, box)[0, 0] == pytest.approx(0.95)
    np.savez(tmp_path / "far.npz", positions=np.array([[-1.5, 0.95], [0.2, 0.1]]), radii=np.full(2, 0.05), box=box)
    assert cli.main(["analyze", str(tmp_path / "far.npz")]) == 2
    err = capsys.readouterr().err
    assert "far outside the tilted cell" in err and "row 0" in err


def test_hoomd_positions_lie_in_hoomds_tilted_box():
    """HOOMD's box is centred: s in [-1/2, 1/2) with r = (Lx s_x + xy Ly s_y, Ly s_y), computed here
    from the float32 values HOOMD reads, and every point is its packing's centre up to float32."""
    from campaign.report.export import hoomd_positions

    rng = np.random.default_rng(4)
    for box in (np.array([1.03, 1 / 1.03, 0.04]), np.array([0.8, 0.69282032, -0.57735027]),
                np.array([2.0, 1.0, 1.0])):
        pos = rng.random((2000, 2)) * box[:2]
        pos[:4] = [[0.0, 0.0], [box[0] * (1 - 1e-17), box[1] * (1 - 1e-17)], [0.5 * box[0], 0.5 * box[1]],
                   [box[0] - 1e-9, 0.0]]
        p32 = hoomd_positions(pos, box)
        assert p32.dtype == np.float32 and p32.shape == (len(pos), 3) and np.all(p32[:, 2] == 0)
        b32 = box.astype(np.float32).astype(np.float64)
        s = _frac(p32[:, :2].astype(np.float64), b32)
        assert np.all(s >= -0.5) and np.all(s < 0.5)
        # the same point as the packing's centre, modulo the lattice, within float32 rounding
        d = _frac(p32[:, :2].astype(np.float64), box) - _frac(pos - 0.5 * (box[:2] + [box[2] * box[1], 0]), box)
        d -= np.round(d)
        assert np.max(np.abs(d)) < 1e-6


def test_a_hoomd_frame_with_a_tilted_box_is_read(tmp_path, capsys):
    """A GSD frame as HOOMD writes it (float32 only, the tilted centred box)."""
    import gsd.hoomd

    from campaign.report.export import hoomd_positions

    pos, rad, box = _sheared()
    fr = gsd.hoomd.Frame()
    fr.configuration.dimensions = 2
    fr.configuration.box = [box[0], box[1], 1.0, box[2], 0.0, 0.0]
    fr.particles.N = len(rad)
    fr.particles.position = hoomd_positions(pos, box)
    fr.particles.diameter = (2 * rad).astype(np.float32)
    with gsd.hoomd.open(str(tmp_path / "h.gsd"), "w") as t:
        t.append(fr)
    c = read_configuration(tmp_path / "h.gsd")
    assert c.box.shape == (3,) and np.array_equal(c.box, box.astype(np.float32).astype(np.float64))
    d = _frac(c.positions, box) - _frac(pos, box)
    d -= np.round(d)
    assert np.max(np.abs(d)) < 1e-6 and "float32" in c.notes[0]
    s = _frac(c.positions, c.box)
    assert np.all(s >= -1e-6) and np.all(s < 1 + 1e-6)  # shifted by (a + b)/2: into the cell


def test_extended_xyz_of_a_tilted_cell(tmp_path, monkeypatch):
    import ase.io as ase_io
    import ase.parallel

    from campaign.report.export import xyz_frame

    monkeypatch.setattr(ase.parallel.world, "comm", ase.parallel.DummyMPI())  # serial, as test_export
    pos, rad, box = _sheared(xy=-0.3, stretch=1.1)
    conf = {"positions": pos, "radii": rad, "box": box, "species": np.zeros(len(rad), np.int64)}
    (tmp_path / "t.xyz").write_text(xyz_frame({"id": "x", "N": len(rad)}, conf, ["A"], 2.0, "shear"))
    atoms = ase_io.read(str(tmp_path / "t.xyz"), format="extxyz")
    assert np.array_equal(atoms.cell.array, [[box[0], 0, 0], [box[2] * box[1], box[1], 0], [0, 0, 1]])
    assert _bits_equal(atoms.positions[:, :2].copy(), pos) and atoms.info["cell"] == "shear"
    c = read_configuration(tmp_path / "t.xyz")
    assert _bits_equal(c.box, box) and _bits_equal(c.positions, pos) and c.cell == "shear"
    # another program's tilted Lattice, no gamma: xy = b_x / Ly
    text = ('2\nLattice="2.0 0 0 0.5 1.25 0 0 0 1" Properties=pos:R:2:radius:R:1\n'
            "0.1 0.1 0.05\n1.5 1.0 0.05\n")
    (tmp_path / "o.xyz").write_text(text)
    c = read_configuration(tmp_path / "o.xyz")
    assert c.box.tolist() == [2.0, 1.25, 0.4] and c.cell is None


# ----------------------------------------------------------------------------- campaign draw


def _by_gid(fig):
    out = {}
    for ax in fig.axes:
        for c in list(ax.collections) + list(ax.patches):
            out.setdefault(c.get_gid(), []).append(c)
    return out


def test_draw_the_triangular_crystal_in_its_tilted_cell(tmp_path, capsys):

    from campaign.report import draw

    pos, rad, box = _crystal()
    n = len(rad)
    sc = draw.scene(pos, rad, box, layers=draw.LAYERS)
    c = sc.counts
    assert (c["N"], c["N_G"], c["N_R"], c["contacts"], c["N_V"], c["N_F"]) == (n, n, 0, 3 * n, 2 * n, 0)
    Lx, Ly, xy = box
    assert sc.window == draw.cell_bounds(box) == (0.0, 0.0, Lx + xy * Ly, Ly)
    s = _frac(sc.disks.primary["centres"], box)
    assert np.all(s > -1e-12) and np.all(s < 1 + 1e-12)  # the primaries in the parallelogram
    # images are translates of primaries by lattice vectors i a + j b
    prim = sc.network.primary["segments"]
    img = sc.network.images["segments"]
    shift = img - prim[sc.network.images["index"]]
    k = _frac(shift.reshape(-1, 2), box)
    assert np.allclose(k, np.round(k), atol=1e-9)
    # the grain and void polygons, primaries and images, tile the window: A_G = 3/4
    x0, y0, x1, y1 = sc.window
    polys = {name: draw._poly_list(p.primary) + draw._poly_list(p.images) for name, p in
             (("grains", sc.grains), ("voids", sc.voids))}
    covered = sum(clipped_area(v, x0, y0, x1, y1) for ps in polys.values() for v in ps)
    assert covered == pytest.approx((x1 - x0) * (y1 - y0), rel=1e-9)
    ga = sum(polygon_area(v) for v in draw._poly_list(sc.grains.primary))
    assert ga / (Lx * Ly) == pytest.approx(0.75, rel=1e-5)
    fig = draw.render(sc)
    arts = _by_gid(fig)
    (cell,) = arts["box"]
    assert np.allclose(cell.get_xy()[:4], [[0, 0], [Lx, 0], [Lx + xy * Ly, Ly], [xy * Ly, Ly]])
    plt.close(fig)
    # from the command line: a text file with the box line 'Lx Ly xy'
    src = tmp_path / "crystal.txt"
    src.write_text(" ".join(repr(float(v)) for v in box) + "\n"
                   + "".join(f"{x!r} {y!r} {r!r}\n" for (x, y), r in zip(pos.tolist(), rad.tolist())))
    out = tmp_path / "crystal.png"
    assert cli.main(["draw", str(src), "--out", str(out)]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG" and f"{3 * n} contacts" in capsys.readouterr().err


def test_region_is_checked_against_the_cells_bounding_box(tmp_path, capsys):
    from campaign.errors import UserError
    from campaign.report import draw

    pos, rad, box = _sheared(xy=-0.3)
    Lx, Ly, xy = box
    assert draw.cell_bounds(box) == (xy * Ly, 0.0, Lx, Ly)
    sc = draw.scene(pos, rad, box, region=(xy * Ly + 0.01, 0.5, 0.2, 0.2))  # left of x = 0, in the cell
    assert sc.window[0] < 0
    with pytest.raises(UserError, match="outside the tilted cell's bounding box"):
        draw.check_window((xy * Ly - 0.2, 0.5, 0.1, 0.1), box)
    W = Lx - xy * Ly  # the bounding box's width
    with pytest.raises(UserError, match="more than one box length beyond"):
        draw.check_window((xy * Ly - W - 0.01, 0.1, W + 0.5, 0.5), box)
    draw.check_window((xy * Ly - W + 0.01, 0.1, W + 0.5, 0.5), box)
    src = tmp_path / "c.npz"
    np.savez(src, positions=pos, radii=rad, box=box)
    assert cli.main(["draw", str(src), "--region", "3", "3", "1", "1", "--out", str(tmp_path / "x.png")]) == 2
    assert "outside the tilted cell's bounding box" in capsys.readouterr().err


def test_the_rectangular_drawing_is_the_tilted_one_at_zero_tilt():
    """The rectangular path (unchanged) and the tilted machinery at xy = 0 draw the same picture."""
    from campaign.report import draw

    rows = [line.split() for line in EXAMPLE.read_text().splitlines() if line and not line.startswith("#")]
    arr = np.array([[float(x) for x in r] for r in rows[1:]])
    box = np.array([float(x) for x in rows[0]])
    for region in (None, (-0.3, 0.25, 1.5, 0.6)):
        rect = draw.scene(arr[:, :2], arr[:, 2], box, region=region, layers=draw.LAYERS)
        tilt0 = draw.scene(arr[:, :2], arr[:, 2], np.append(box, 0.0), region=region, layers=draw.LAYERS)
        assert rect.window == tilt0.window and rect.counts == tilt0.counts
        for name in ("disks", "network", "grains"):
            for part in ("primary", "images"):
                a, b = getattr(getattr(rect, name), part), getattr(getattr(tilt0, name), part)
                key = {"disks": "centres", "network": "segments", "grains": "verts"}[name]
                flat = lambda d: np.sort(np.round(d[key].reshape(len(d[key]), -1), 12), axis=0)  # noqa: E731
                assert np.allclose(flat(a), flat(b), atol=1e-12), (name, part)
        fig = draw.render(rect)
        assert type(_by_gid(fig)["box"][0]).__name__ == "Rectangle"
        plt.close(fig)


# ----------------------------------------------------------------------------- a campaign of both cells

REAL_SPEC = """\
name: tilted
seed: 5
grid: {N_G: [32], E_G: [1.0e-8, 1.0e-4], seeds: 2}
protocol: {cell: fixed}
variants:
  - {name: shear, cell: shear}
  - {name: shear-ladder, cell: shear, start: ladder}
observables: [scalars, connectivity, moduli]
store: {configurations: true}
"""


def _run(spec_text, d, name, *extra):
    spec, out = d / f"{name}.yaml", d / f"{name}.h5"
    spec.write_text(spec_text)
    assert cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--quiet", *extra]) == 0
    return out


def _h5(path):
    with h5py.File(path, "r", locking=False) as f:
        t = {k: f[f"tasks/{k}"][:] for k in ("id", "variant", "N", "E", "seed", "status")}
        t["id"], t["variant"] = t["id"].astype(str), t["variant"].astype(str)
        s = {k: f[f"scalars/{k}"][:] for k in f["scalars"]}
        boxes = {tid: f[f"configurations/{tid}/box"][()] for tid in f.get("configurations", {})}
    return t, s, boxes


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """A real campaign (kernels, cell shear): N_G = 32 at 1e-8 and 1e-4, fixed and shear cells."""
    return _run(REAL_SPEC, tmp_path_factory.mktemp("real"), "real")


@pytest.mark.slow  # a real campaign in a tilted cell (about half a minute cold): --full
def test_every_packing_stores_its_tilt_and_shear_stress(real):
    t, s, boxes = _h5(real)
    assert np.all(t["status"] == 1) and np.all(s["jam_status"] == 0) and np.all(s["identities_ok"] == 1)
    for r, tid in enumerate(t["id"]):
        box, N_G = boxes[tid], s["N_G"][r]
        if t["variant"][r] == "default":  # the fixed cell
            assert box.shape == (2,) and s["gamma"][r] == 0.0 and np.isfinite(s["sigma_xy"][r])
            assert s["z_iso"][r] == 4 - 2 / N_G
        else:
            assert box.shape == (3,) and _bits_equal(s["gamma"][r], box[2]) and box[2] != 0
            assert box[0] * box[1] == pytest.approx(1.0, rel=1e-12)  # the area is kept
            assert abs(s["sigma_xy"][r]) <= 1e-4 * s["pressure"][r]
            assert s["z_iso"][r] == 4 + 2 / N_G
            assert s["N_C"][r] / 2 >= 2 * N_G + 1  # at least isostatic in the shear-stabilised count


@pytest.mark.slow  # a real campaign in a tilted cell (about half a minute cold): --full
@pytest.mark.parametrize("fmt", ["gsd", "xyz"])
def test_an_exported_tilted_frame_analyses_to_the_stores_scalars(real, tmp_path, capsys, fmt):
    out = tmp_path / f"p.{fmt}"
    assert cli.main(["export", str(real), "--out", str(out)]) == 0
    capsys.readouterr()
    t, s, boxes = _h5(real)
    rows = np.flatnonzero(t["status"] == 1)
    for k, r in enumerate(rows):
        assert cli.main(["analyze", str(out), "--frame", str(k), "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
        for name in ("N_G", "N_C", "E_G", "pressure", "A_G", "psi_O", "z_iso", "delta_Z", "gamma", "sigma_xy"):
            assert got[name] == s[name][r], (fmt, t["variant"][r], name)
    if fmt == "gsd":
        import gsd.hoomd

        with gsd.hoomd.open(str(out), "r") as traj:
            for k, r in enumerate(rows):
                fr, box = traj[k], boxes[t["id"][r]]
                xy = box[2] if len(box) > 2 else 0.0
                assert np.array_equal(fr.configuration.box, np.array([box[0], box[1], 1, xy, 0, 0], np.float32))
                assert _bits_equal(fr.log["campaign/box64"], box)  # the stored box as it is
                b32 = np.append(box[:2], xy).astype(np.float32).astype(np.float64)
                f = _frac(fr.particles.position[:, :2].astype(np.float64), b32)
                assert np.all(f >= -0.5) and np.all(f < 0.5)
                cell = bytes(fr.log["campaign/cell"].astype(np.uint8)).decode()
                assert cell == ("shear" if len(box) > 2 else "fixed")
    # the human output shows the tilt
    assert cli.main(["analyze", str(out), "--frame", "-1"]) == 0
    assert "tilt xy = " in capsys.readouterr().out


@pytest.mark.slow  # a real campaign in a tilted cell (about half a minute cold): --full
def test_a_stored_configuration_read_in_place_knows_its_cell(real, capsys):
    t, s, boxes = _h5(real)
    for r in (int(np.flatnonzero(t["variant"] == v)[0]) for v in ("default", "shear")):
        group = f"/configurations/{t['id'][r]}"
        c = read_configuration(real, group=group)
        assert c.cell == ("shear" if t["variant"][r] == "shear" else "fixed") and _bits_equal(c.box, boxes[t["id"][r]])
        assert cli.main(["analyze", str(real), "--group", group, "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
        for name in ("N_C", "E_G", "z_iso", "delta_Z", "gamma", "sigma_xy"):
            assert got[name] == s[name][r], name


@pytest.mark.slow  # a real campaign in a tilted cell (about half a minute cold): --full
def test_read_packings_reduce_verify_and_draw(real, tmp_path, capsys):
    import campaign
    from campaign.results import tradeoff
    from campaign.report.frames import Packings
    from campaign.results.finished import load_finished
    from campaign.results.reduce import Settings, reduce_campaign

    t, s, boxes = _h5(real)
    df = campaign.read_packings(real)
    assert _bits_equal(df["gamma"].to_numpy(), s["gamma"]) and _bits_equal(df["sigma_xy"].to_numpy(), s["sigma_xy"])
    with Packings(real) as pk:
        for tid, box in boxes.items():
            assert _bits_equal(pk.configuration(tid)["box"], box)
    red = reduce_campaign(real, Settings(n_boot=20))
    assert "mean_gamma" in red.cells and "mean_sigma_xy" in red.cells
    rec = {r["variant"]: r for r in red.tradeoff}
    assert rec["shear"]["n_pairs"] == 4
    # the isostatic excess counts 2 N_G + 1 contacts in the shear-stabilised cell
    fin = load_finished(real)
    cols = tradeoff._per_packing(fin)[0]
    shear = np.char.startswith(np.asarray(fin.variant, str), "shear")
    want = np.where(shear, fin.scalars["N_C"] / 2 - (2 * fin.scalars["N_G"] + 1),
                    fin.scalars["N_C"] / 2 - (2 * fin.scalars["N_G"] - 1))
    assert np.array_equal(cols["iso_excess"], want)
    assert cli.main(["reduce", str(real), "--out", str(tmp_path / "red"), "--boot", "20"]) == 0
    assert cli.main(["verify", str(real)]) == 0
    capsys.readouterr()
    row = int(np.flatnonzero(t["variant"] == "shear")[0])
    png = tmp_path / "shear.png"
    assert cli.main(["draw", str(real), "--index", str(row), "--out", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"


# ----------------------------------------------------------------------------- an older store


class WithCell(SyntheticTask):
    """The synthetic task of a version that stores the cell's tilt and shear stress."""

    def run(self, payload, context):
        scalars, hists, config = super().run(payload, context)
        scalars.update(gamma=0.0, sigma_xy=1e-9 * (payload["seed"] + 1))
        return scalars, hists, config


OLD_SPEC = """\
name: older
seed: 3
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 4}
observables: [scalars, connectivity]
run: {retries: 0}
"""


def test_a_store_written_before_gamma_resumes_and_reduces(tmp_path, capsys, monkeypatch):
    import campaign
    from campaign.results.reduce import Settings, reduce_campaign

    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", "seed:1")
    out = _run(OLD_SPEC, tmp_path, "older", "--task-function", "synthetic")
    t, s, _ = _h5(out)
    assert "gamma" not in s and "sigma_xy" not in s and np.any(t["status"] == 2)
    assert "gamma" not in campaign.read_packings(out).columns
    reduce_campaign(out, Settings(n_boot=5))
    # a newer version finishes the failed packings into the same store
    monkeypatch.delenv("CAMPAIGN_SYNTHETIC_FAIL")
    _run(OLD_SPEC, tmp_path, "older", "--task-function", "test_tilted_campaign:WithCell", "--retry-failed")
    t2, s2, _ = _h5(out)
    assert np.all(t2["status"] == 1)
    new = t["status"] == 2
    assert np.all(np.isnan(s2["gamma"][~new])) and np.all(s2["gamma"][new] == 0.0)
    assert _bits_equal(s2["sigma_xy"][new], 1e-9 * (t["seed"][new] + 1))
    assert _bits_equal(s2["A_G"][~new], s["A_G"][~new])  # the older rows as they were
    df = campaign.read_packings(out)
    assert df["gamma"].isna().sum() == np.count_nonzero(~new)
    red = reduce_campaign(out, Settings(n_boot=5))
    assert np.all(np.isfinite(red.cells["mean_gamma"]))  # the new rows' mean, NaN rows left out
    assert cli.main(["reduce", str(out), "--out", str(tmp_path / "red"), "--boot", "20"]) == 0
    assert cli.main(["verify", str(out)]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("n", [2, 3])
def test_the_same_bits_with_one_two_and_three_workers(real, tmp_path, n):
    """Both cells and the shear ladder under mpiexec -n 2 and -n 3 (oversubscribed): every stored
    array as in the one-process run, but where and when each task ran."""
    import os
    import subprocess
    import sys

    mpiexec = Path(sys.executable).parent / "mpiexec"
    spec, out = tmp_path / "real.yaml", tmp_path / "real.h5"
    spec.write_text(REAL_SPEC)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    proc = subprocess.run([str(mpiexec), "-n", str(n), sys.executable, "-m", "campaign", "run", str(spec),
                           "--out", str(out), "--quiet"], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]

    def datasets(path):
        got = {}
        with h5py.File(path, "r", locking=False) as f:
            f.visititems(lambda k, o: got.__setitem__(k, o[()]) if isinstance(o, h5py.Dataset) else None)
        return got

    a, b = datasets(real), datasets(out)
    assert set(a) == set(b)
    for k in a:
        if k not in ("tasks/wall", "tasks/rank", "tasks/host", "checksums/tasks.wall", "checksums/tasks.rank",
                     "checksums/tasks.host") and not k.endswith("_seconds"):
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k
