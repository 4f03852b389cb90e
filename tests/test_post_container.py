"""``mpipack post`` inside a container (post/container.py): known answers and rank independence.

(a) the pieces: a cap against its integral, a cylinder side's cut against scipy's adaptive
    quadrature (1e-8 of the ball) and against itself with 4x the nodes (1e-12), and against a
    plane's cap as the cylinder's radius grows;
(b) hand-made packings with known answers: a simple cubic lattice filling a box exactly
    (packing fraction pi/6, 2D square pi/4, to 1e-12; every slab along z pi/6; the wall
    profile's first bin the slab average of a touching layer, its centres at 0.5, 1.5, ... d);
    one sphere cut by the floor (its ball less its cap); one sphere in a sphere container (the
    lens); the wall contacts from wall_force;
(c) the same JSON and CSV files on 1, 2, 3 ranks: a hand-made cylinder packing with spheres
    through its side, floor and lid, and a real container run.
"""

import json
import math
import sys

import numpy as np
import pytest

from conftest import describe, mpipack_run, mpirun

from mpipack.post import container as box


def analysis(x, diam, container, fields=None):
    from mpipack.parallel.comm import Comm
    from mpipack.post.analysis import Analysis
    from mpipack.post.source import Packing
    x = np.ascontiguousarray(x, dtype=np.float64)
    n, dim = x.shape
    pk = Packing(n=n, dim=dim, gid=np.arange(n, dtype=np.int64), x=x, diam=np.asarray(diam, dtype=np.float64),
                 fields=fields or {}, pairs=None, iteration=0, attrs={}, scene={"container": container},
                 path="", kind="arrays", summary={})
    return Analysis(Comm.serial(), pk, 1.1 * float(np.max(diam)))


def lattice(m, dim):
    g = np.arange(m) + 0.5
    return np.stack(np.meshgrid(*([g] * dim), indexing="ij"), axis=-1).reshape(-1, dim)


# ---- (a) the pieces ----------------------------------------------------------------------------------

@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("h", [1e-4, 0.1, 0.5, 0.9])
def test_cap_is_its_integral(dim, h):
    from scipy import integrate
    r = 0.5
    slice_measure = {1: lambda u: 1.0, 2: lambda u: 2 * math.sqrt(max(r * r - u * u, 0.0)),
                     3: lambda u: math.pi * (r * r - u * u)}[dim]
    ref = integrate.quad(slice_measure, r - h, r, epsabs=1e-15, epsrel=1e-13)[0]
    assert box.cap(dim, r, h) == pytest.approx(ref, rel=1e-10, abs=1e-15)


@pytest.mark.parametrize("rho", [2.55, 2.6, 2.8, 3.0, 3.3, 3.6])
def test_cylinder_cut_against_scipy_and_itself(rho, monkeypatch):
    from scipy import integrate
    r, big = 0.5, 3.0
    ball = 4.0 / 3.0 * math.pi * r ** 3
    got = box.cylinder_cut(r, rho, big)

    def chord(rp, th):  # the ball's chord along z above the point (rp, th) outside the circle
        return 2 * math.sqrt(max(r * r - (rp * math.cos(th) - rho) ** 2 - (rp * math.sin(th)) ** 2, 0.0)) * rp

    th0 = math.asin(min(r / rho, 1.0))

    def half(th):  # the chord's half extent along the ray at angle th about the sphere's centre
        return math.sqrt(max(r * r - (rho * math.sin(th)) ** 2, 0.0))

    ref = integrate.dblquad(chord, -th0, th0, lambda th: max(big, rho * math.cos(th) - half(th)),
                            lambda th: rho * math.cos(th) + half(th), epsabs=1e-14, epsrel=1e-12)[0]
    assert abs(got - ref) < 1e-8 * ball, (got, ref)
    monkeypatch.setattr(box, "QUADRATURE", 4 * box.QUADRATURE)
    monkeypatch.setattr(box, "_NODES", None)
    assert abs(got - box.cylinder_cut(r, rho, big)) < 1e-12 * ball


def test_a_wide_cylinder_cuts_like_a_plane():
    r, h = 0.5, 0.05
    for big in (1e2, 1e4, 1e6):  # the wall bends towards the sphere by y^2 / (2 big), y^2 <= 2 r h
        assert box.cylinder_cut(r, big + h - r, big) == pytest.approx(box.cap(3, r, h), rel=4 * r / big)


# ---- (b) known answers -------------------------------------------------------------------------------

def test_simple_cubic_lattice_filling_a_box():
    m = 6
    a = analysis(lattice(m, 3), np.ones(m ** 3), {"kind": "box", "lo": [0, 0, 0], "hi": [m, m, m]})
    d = a.density()
    c = d.summary["container"]
    assert c["packing_fraction"] == pytest.approx(math.pi / 6, abs=1e-12)
    assert c["volume"] == m ** 3 and c["axis_profile"]["slabs"] == m
    axis = d.parts["axis"][0]
    assert np.allclose(axis["phi"], math.pi / 6, atol=1e-12, rtol=0)
    wall = d.parts["wall-pooled"][0]
    # a touching layer's slab average over [0, d/10): pi (t - t^2) integrated, over d/10
    first = math.pi * (0.1 ** 2 / 2 - 0.1 ** 3 / 3) / 0.1
    assert wall["phi"][0] == pytest.approx(first, abs=1e-12)
    assert np.allclose(wall["phi"][:10], wall["phi"][10:20], atol=1e-12)  # layer after layer
    layers = [5, 15, 25, 35, 45]  # each wall's layers at 0.5, 1.5, ... 4.5 d
    assert np.flatnonzero(wall["centres"]).tolist() == layers and set(wall["centres"][layers]) == {6 * m * m}
    assert c["wall_profile_pooled"]["centres_first_peak_t_over_d"] == pytest.approx(0.55)
    # from the nearest wall: the shells of a 6^3 box, the layers' centres at 0.5, 1.5, 2.5 d
    near = d.parts["wall"][0]
    assert np.allclose(near["shell"][:30], [(m - 2 * a) ** 3 - (m - 2 * b) ** 3 for a, b in
                                            zip(near["t_from"][:30], near["t_to"][:30])], rtol=1e-12)
    assert (near["shell"][30:] == 0).all() and np.isnan(near["phi"][30:]).all()
    assert near["centres"][[5, 15, 25]].tolist() == [m ** 3 - 4 ** 3, 4 ** 3 - 2 ** 3, 2 ** 3]
    assert near["covered"].sum() == pytest.approx(m ** 3 * math.pi / 6, rel=1e-12)  # every ball, all the way in
    assert d.warnings == []


def test_square_lattice_in_a_2d_box():
    m = 5
    d = analysis(lattice(m, 2), np.ones(m * m), {"kind": "box", "lo": [0, 0], "hi": [m, m]}).density()
    assert d.summary["container"]["packing_fraction"] == pytest.approx(math.pi / 4, abs=1e-12)
    assert np.allclose(d.parts["axis"][0]["phi"], math.pi / 4, atol=1e-12, rtol=0)


def test_a_sphere_cut_by_the_floor():
    r, z = 0.5, 0.3
    x = np.array([[5.0, 5.0, z]])
    full = 4 / 3 * math.pi * r ** 3
    cap = math.pi * (r - z) ** 2 * (3 * r - (r - z)) / 3
    for table in ({"kind": "box", "lo": [0, 0, 0], "hi": [10, 10, 10]},
                  {"kind": "cylinder", "centre": [5, 5, 0], "radius": 4.0, "height": None}):
        c = analysis(x, [2 * r], table).density().summary["container"]
        assert c["covered"] == pytest.approx(full - cap, rel=1e-13), table
        assert c["side_walls_cut"] == 0.0
    # and through the cylinder's side: the quadrature's cut
    x = np.array([[5.0 + 4.0 - 0.3, 5.0, 2.0]])
    c = analysis(x, [1.0], {"kind": "cylinder", "centre": [5, 5, 0], "radius": 4.0, "height": 5.0}).density()
    cut = box.cylinder_cut(0.5, 3.7, 4.0)
    assert c.summary["container"]["covered"] == pytest.approx(full - cut, rel=1e-13)
    assert c.summary["container"]["side_walls_cut"] == pytest.approx(cut, rel=1e-13)


def test_a_sphere_in_a_sphere_container_is_a_lens():
    from mpipack.kernels import metrics
    big, r = 3.0, 0.5
    x = np.array([[0.0, 0.0, big - 0.4], [0.0, 0.0, 0.0]])
    c = analysis(x, [1.0, 1.0], {"kind": "sphere", "centre": [0, 0, 0], "radius": big}).density().summary["container"]
    lens = metrics.intersection(3, big - 0.4, r, big)
    assert lens < 4 / 3 * math.pi * r ** 3
    assert c["covered"] == pytest.approx(lens + 4 / 3 * math.pi * r ** 3, rel=1e-14)
    assert c["packing_fraction"] == pytest.approx(c["covered"] / (4 / 3 * math.pi * big ** 3), rel=1e-14)


def test_wall_contacts_from_the_wall_force():
    x = lattice(3, 3)
    wf = np.zeros(len(x))
    wf[[0, 5, 7]] = [1.0, 2.0, 6.0]
    m, _ = analysis(x, np.ones(len(x)), {"kind": "box", "lo": [0, 0, 0], "hi": [3, 3, 3]},
                    fields={"wall_force": wf}).contacts()
    w = m.summary["walls"]
    assert w["by_wall_force"] == 3 and w["mean_wall_force"] == 3.0 and w["max_wall_force"] == 6.0
    assert w["by_gap"] == 26  # every sphere but the middle one touches a wall
    m, _ = analysis(x, np.ones(len(x)), {"kind": "box", "lo": [0, 0, 0], "hi": [3, 3, 3]}).contacts()
    assert "by_wall_force" not in m.summary["walls"] and any("wall_force" in s for s in m.warnings)


# ---- (c) the same on 1, 2, 3 ranks -----------------------------------------------------------------

CYLINDER = {"kind": "cylinder", "centre": [0.0, 0.0, 0.0], "radius": 3.0, "height": 4.0}


def hand_made_cylinder():
    """Spheres on a jittered lattice in the cylinder, some through its side, floor and lid."""
    rng = np.random.default_rng(4)
    g = np.arange(-3.0, 3.01, 0.95)
    x = np.array([(a, b, z) for z in (0.42, 1.4, 2.4, 3.58) for a in g for b in g if math.hypot(a, b) < 3.0])
    x += rng.normal(scale=0.01, size=x.shape)
    diam = rng.uniform(0.9, 1.0, len(x))
    return x, diam


def write_snapshot(path, x, diam, scene, fields):
    from mpipack.io import SnapshotWriter
    from mpipack.parallel.comm import Comm
    n, dim = x.shape
    with SnapshotWriter(Comm.serial(), str(path), n, dim, {"scene": json.dumps(scene)}, xdmf=False) as w:
        w.write(np.arange(n), {"position": x, "diameter": diam, **fields}, {"iteration": 9})


def post_on(ranks, run, out, measures="density,contacts"):
    proc = mpirun(ranks, [sys.executable, "-m", "mpipack.cli", "post", measures, run, "--out", out], out.parent,
                  timeout=300)
    assert proc.returncode == 0, describe(proc)
    return proc


def outputs(out):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".json", ".csv")}


@pytest.mark.mpi
def test_hand_made_cylinder_the_same_on_1_2_3_ranks(tmp_path):
    x, diam = hand_made_cylinder()
    s = box.gaps(box.of_scene({"container": CYLINDER}, 3).walls, x)
    assert ((s < 0.5 * diam[:, None]).sum(axis=0) > 0).all()  # the side, floor and lid each cut a sphere
    wf = np.where((s - 0.5 * diam[:, None] < 0).any(axis=1), 1.0 + np.arange(len(x)) / len(x), 0.0)
    write_snapshot(tmp_path / "snapshots.h5", x, diam, {"container": CYLINDER}, {"wall_force": wf})
    got = {}
    for ranks in (1, 2, 3):
        post_on(ranks, tmp_path / "snapshots.h5", tmp_path / f"np{ranks}")
        got[ranks] = outputs(tmp_path / f"np{ranks}")
    assert {"density.json", "density-axis.csv", "density-wall.csv", "density-wall-pooled.csv",
            "contacts.json"} <= set(got[1])
    assert got[2] == got[1] and got[3] == got[1]
    c = json.loads(got[1]["density.json"])["summary"]["container"]
    full = (math.pi / 6 * diam ** 3).sum()
    # C_t is empty from t = 3 on: the profile holds every ball's part inside, exact also for the 10
    # balls through the side and the floor or lid at once (covered takes their cuts' overlap twice)
    assert c["wall_profile"]["clip_height"] is None
    assert any("overlap" in w for w in json.loads(got[1]["density.json"])["warnings"])
    assert c["covered"] < c["wall_profile"]["covered"] < c["covered"] + 0.005
    assert 0 < full - c["covered"] < 0.2 * full and c["side_walls_cut"] > 0
    assert c["packing_fraction"] == pytest.approx(c["covered"] / (math.pi * 9 * 4), rel=1e-14)
    assert c["axis_profile"]["slabs"] == math.ceil(4 / (diam.mean()) - 1e-9)
    w = json.loads(got[1]["contacts.json"])["summary"]["walls"]
    assert w["by_wall_force"] == int((wf > 0).sum()) and w["mean_wall_force"] == pytest.approx(wf[wf > 0].mean())


@pytest.mark.mpi
def test_open_cylinder_nearest_wall_profile_the_same_on_1_2_3_ranks(tmp_path):
    """The hand-made cylinder without its lid, the top layer's spheres 1 d higher (a free surface):
    the nearest-wall profile stops 2 d under it; the same files on 1, 2, 3 ranks."""
    x, diam = hand_made_cylinder()
    x[x[:, 2] > 3, 2] += 1.0
    scene = {"container": dict(CYLINDER, height=None)}
    write_snapshot(tmp_path / "snapshots.h5", x, diam, scene, {})
    got = {}
    for ranks in (1, 2, 3):
        post_on(ranks, tmp_path / "snapshots.h5", tmp_path / f"np{ranks}", "density")
        got[ranks] = outputs(tmp_path / f"np{ranks}")
    assert got[2] == got[1] and got[3] == got[1]
    w = json.loads(got[1]["density.json"])["summary"]["container"]["wall_profile"]
    surface = (x[:, 2] + 0.5 * diam).max()
    assert w["clip_height"] == pytest.approx(surface - 2 * diam.mean(), rel=1e-14) and "below clip_height" in w["region"]
    assert w["shells"] == pytest.approx(math.pi * 9 * w["clip_height"], rel=1e-12)  # all of it within 5 d of a wall
    rows = got[1]["density-wall.csv"].decode().splitlines()
    assert rows[0] == "t_from,t_to,t_over_d,covered,shell,phi,centres" and len(rows) == 51


REAL = ("dim=3", "n=80", "container.kind=cylinder", "container.centre=[0,0,0]", "container.radius=2.6",
        "container.height=4", "stop.max_iter=400")


@pytest.mark.mpi
def test_a_real_container_run_the_same_on_1_2_3_ranks(tmp_path):
    proc, summary, _ = mpipack_run(2, tmp_path, sets=REAL)
    assert proc.returncode in (0, 4), describe(proc)
    got = {}
    for ranks in (1, 2, 3):
        post_on(ranks, tmp_path / "out", tmp_path / f"np{ranks}")
        got[ranks] = outputs(tmp_path / f"np{ranks}")
    assert got[2] == got[1] and got[3] == got[1]
    doc = json.loads(got[1]["density.json"])
    c = doc["summary"]["container"]
    assert 80 * math.pi / 6 * 0.99 < c["covered"] <= 80 * math.pi / 6 and c["volume"] == pytest.approx(math.pi * 2.6 ** 2 * 4)
    assert 0.3 < c["packing_fraction"] < 0.7405
    w = json.loads(got[1]["contacts.json"])["summary"]["walls"]
    assert w["by_wall_force"] > 0 and w["mean_wall_force"] > 0


# ---- (d) the profile from the nearest wall ------------------------------------------------------------

def test_a_ball_in_a_shrunk_container_against_closed_forms_and_itself(monkeypatch):
    from scipy import integrate
    r = 0.5
    full = 4 / 3 * math.pi * r ** 3
    c = box.of_scene({"container": {"kind": "box", "lo": [0, 0, 0], "hi": [4, 4, 4]}}, 3)
    for z in (0.25, 0.5, 0.7):  # one wall of C_0.2 through the ball: the ball less its cap
        got = box.ball_in_shrunk(c, 3, np.array([2.0, 2.0, z]), r, 0.2)
        assert got == pytest.approx(full - box.cap(3, r, r - (z - 0.2)), abs=1e-14)
    cy = box.of_scene({"container": {"kind": "cylinder", "centre": [0, 0, 0], "radius": 3.0, "height": None}}, 3)
    for rho in (2.55, 3.0, 3.3):  # through the side: the quadrature's cut
        got = box.ball_in_shrunk(cy, 3, np.array([0.0, rho, 5.0]), r, 0.0, clip=9.0)
        assert got == pytest.approx(full - box.cylinder_cut(r, rho, 3.0), abs=1e-14)
    # a ball in a shrunk box's corner (three planes) and a cylinder's rim (side, floor, clip)
    cases = [(c, np.array([0.55, 0.62, 0.41])), (cy, np.array([0.0, 2.5, 0.45])), (cy, np.array([2.5, 0.3, 4.2]))]
    got = [box.ball_in_shrunk(k, 3, p, r, 0.2, clip=4.3) for k, p in cases]
    for k, (p, v) in enumerate(zip(cases, got)):
        if k == 0:  # the corner's volume against a slice-by-slice integral of the disc's quadrant part
            def slice_area(z, p=p[1]):
                a = math.sqrt(max(r * r - (z - p[2]) ** 2, 0.0))
                return float(box.disc_in_rectangle(np.array([a]), 0.2 - p[0], 3.8 - p[0], 0.2 - p[1], 3.8 - p[1])[0])
            ref = integrate.quad(slice_area, 0.2, p[1][2] + r, epsabs=1e-14, epsrel=1e-13, limit=400)[0]
            assert v == pytest.approx(ref, abs=1e-11)
        assert 0 < v < full
    monkeypatch.setattr(box, "QUADRATURE", 4 * box.QUADRATURE)
    monkeypatch.setattr(box, "_NODES", None)
    assert np.allclose(got, [box.ball_in_shrunk(k, 3, p, r, 0.2, clip=4.3) for k, p in cases], atol=1e-12 * full, rtol=0)


def test_disc_in_a_rectangle_against_quadrature():
    from scipy import integrate
    rng = np.random.default_rng(7)
    for _ in range(100):
        a = rng.uniform(0.05, 1.0)
        x1, x2 = np.sort(rng.uniform(-1.2, 1.2, 2))
        y1, y2 = np.sort(rng.uniform(-1.2, 1.2, 2))
        chord = lambda x: max(0.0, min(y2, math.sqrt(max(a * a - x * x, 0))) - max(y1, -math.sqrt(max(a * a - x * x, 0))))
        kinks = [s * math.sqrt(max(a * a - y * y, 0.0)) for s in (-1, 1) for y in (y1, y2)]
        lo, hi = max(x1, -a), min(x2, a)
        ref = integrate.quad(chord, lo, hi, points=kinks, epsabs=1e-15, epsrel=1e-13, limit=200)[0] if hi > lo else 0.0
        assert box.disc_in_rectangle(np.array([a]), x1, x2, y1, y2)[0] == pytest.approx(ref, abs=1e-12)


def test_nearest_wall_profile_of_a_filled_box_adds_up():
    """A simple cubic lattice filling a 12^3 box: the profile times the shells adds up to the balls'
    measure within 5 d of the walls: all but the 8 balls inside [5, 7]^3 (C_5)."""
    m = 12
    d = analysis(lattice(m, 3), np.ones(m ** 3), {"kind": "box", "lo": [0, 0, 0], "hi": [m, m, m]}).density()
    near = d.parts["wall"][0]
    w = d.summary["container"]["wall_profile"]
    assert w["clip_height"] is None and w["region"] == "the container"
    assert np.nansum(near["phi"] * near["shell"]) == pytest.approx((m ** 3 - 8) * math.pi / 6, rel=1e-12)
    assert w["covered"] == pytest.approx(d.summary["container"]["covered"] - 8 * math.pi / 6, rel=1e-12)
    assert w["shells"] == pytest.approx(m ** 3 - 2 ** 3, rel=1e-14)
    # layer after layer: the same shape within 1 % (not exactly: the shells bend at the box's edges)
    assert np.allclose(near["phi"][:10], near["phi"][10:20], atol=0.01, rtol=0)
    assert np.argmax(near["phi"][:10]) == 4 and w["first_peak_t_over_d"] % 1.0 == pytest.approx(0.45)


def test_nearest_wall_profile_in_2d_and_in_a_sphere():
    """2D: a square lattice filling a 12 x 12 box adds up to all discs but the 4 inside C_5; a
    sphere container has one wall, so its nearest-wall profile is its pooled one."""
    m = 12
    d = analysis(lattice(m, 2), np.ones(m * m), {"kind": "box", "lo": [0, 0], "hi": [m, m]}).density()
    w = d.summary["container"]["wall_profile"]
    assert w["covered"] == pytest.approx((m * m - 4) * math.pi / 4, rel=1e-12) and w["shells"] == pytest.approx(m * m - 4)
    rng = np.random.default_rng(3)
    x = rng.normal(size=(400, 3))
    x *= (rng.uniform(0, 1, 400) ** (1 / 3) * 3.4 / np.linalg.norm(x, axis=1))[:, None]
    d = analysis(x, np.full(400, 0.4), {"kind": "sphere", "centre": [0, 0, 0], "radius": 3.5}).density()
    near, pooled = d.parts["wall"][0], d.parts["wall-pooled"][0]
    assert np.allclose(near["covered"], pooled["covered"], rtol=1e-12, atol=1e-14)
    assert np.allclose(near["shell"], pooled["shell"], rtol=1e-12, atol=0)
    assert (near["centres"] == pooled["centres"]).all() and near["covered"].sum() > 0


def test_nearest_wall_profile_of_a_layer_on_the_floor():
    """Balls of diameter 1 in one layer on the floor (centres at z = 0.5) of an 8 x 8 x 2.5 box, 1 d
    from the side walls: a point of a ball at height z < 1 has its nearest wall below it, so the bin
    [t_1, t_2) covers n pi int_t1^t2 (1/4 - (z - 1/2)^2) dz of the shell (8 - 2 t)^2 (2.5 - 2 t)
    between C_t1 and C_t2."""
    g = np.arange(1, 7) + 0.5
    x = np.array([(a, b, 0.5) for a in g for b in g])
    d = analysis(x, np.ones(len(x)), {"kind": "box", "lo": [0, 0, 0], "hi": [8, 8, 2.5]}).density()
    near = d.parts["wall"][0]
    assert d.summary["container"]["wall_profile"]["clip_height"] is None  # the layer fills the box to 2 d of its top

    def within(t):
        return (8 - 2 * t) ** 2 * (2.5 - 2 * t)

    for q in range(10):
        t1, t2 = near["t_from"][q], near["t_to"][q]
        layer = len(x) * math.pi * (0.25 * (t2 - t1) - ((t2 - 0.5) ** 3 - (t1 - 0.5) ** 3) / 3)
        assert near["phi"][q] == pytest.approx(layer / (within(t1) - within(t2)), rel=1e-12), q
    q = 4  # t in [0.4, 0.5): 36 pi (0.025 - 0.001 / 3) / (7.2^2 1.7 - 7^2 1.5)
    assert near["phi"][q] == pytest.approx(36 * math.pi * (0.025 - 0.001 / 3) / (7.2 ** 2 * 1.7 - 49 * 1.5), rel=1e-12)
    assert (near["covered"][10:] == 0).all() and near["centres"][5] == len(x)


def random_balls(c, inside, n, rng, lo, hi):
    """Non-overlapping balls (diameters 0.8 to 1) placed at random: each centre at inside(p, r)."""
    x, diam = [], []
    for _ in range(200 * n):
        r = 0.5 * rng.uniform(0.8, 1.0)
        p = rng.uniform(lo, hi)
        if inside(p, r) and all(np.linalg.norm(p - q) >= r + 0.5 * e for q, e in zip(x, diam)):
            x.append(p)
            diam.append(2 * r)
            if len(x) == n:
                break
    return np.array(x), np.array(diam)


@pytest.mark.parametrize("kind", ["box", "open cylinder"])
def test_nearest_wall_profile_against_monte_carlo(kind):
    """A random packing; 1e6 points uniform in the region: the share covered in each bin of the
    nearest wall's distance (d/2 wide) within 3 sigma of the profile, and the points' share in
    each shell within 3 sigma of the shell's measure."""
    from scipy.spatial import cKDTree
    from mpipack.parallel.comm import Comm
    rng = np.random.default_rng(11)
    if kind == "box":
        c = box.of_scene({"container": {"kind": "box", "lo": [0, 0, 0], "hi": [5, 5, 4]}}, 3)
        clip, lo, hi = None, np.zeros(3), np.array([5.0, 5.0, 4.0])
        x, diam = random_balls(c, lambda p, r: (box.gaps(c.walls, p[None])[0] >= r).all(), 60, rng, lo, hi)
        region = 100.0
    else:  # the clip at z = 4 cuts balls; the free surface is no wall
        c = box.of_scene({"container": {"kind": "cylinder", "centre": [0, 0, 0], "radius": 2.6, "height": None}}, 3)
        clip, lo, hi = 4.0, np.array([-2.6, -2.6, 0.0]), np.array([2.6, 2.6, 5.0])
        x, diam = random_balls(c, lambda p, r: (box.gaps(c.walls, p[None])[0] >= r - 0.05).all(), 70, rng, lo, hi)
        region = math.pi * 2.6 ** 2 * clip
        assert ((x[:, 2] - 0.5 * diam < clip) & (x[:, 2] + 0.5 * diam > clip)).sum() >= 3
    d_mean = diam.mean()
    edges = np.arange(51) * (d_mean / 10)
    covered, shell, _ = box.nearest_wall_profile(Comm.serial(), c, 3, x, diam, edges, clip)
    assert shell.sum() + box.shrunk_measure(c, 3, edges[-1], clip) == pytest.approx(region, rel=1e-12)
    # the points: uniform in the region (the cylinder's by rejection)
    pts = rng.uniform(lo, [hi[0], hi[1], clip if clip else hi[2]], size=(1_400_000, 3))
    if kind != "box":
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < 2.6]
    pts = pts[:1_000_000]
    assert len(pts) == 1_000_000
    near = box.gaps(c.walls, pts).min(axis=1)
    dist, j = cKDTree(x).query(pts, k=4, distance_upper_bound=0.5)
    hit = (dist < 0.5 * np.append(diam, 0.0)[j]).any(axis=1)
    coarse = np.minimum(np.floor(near / (5 * edges[1])).astype(int), 10)  # 10 bins of d/2, 10: beyond 5 d
    for q in range(10):
        inside = coarse == q
        share = inside.mean()
        expected = shell[5 * q:5 * q + 5].sum() / region
        assert abs(share - expected) <= 3 * math.sqrt(expected * (1 - expected) / len(pts)), (q, share, expected)
        if shell[5 * q:5 * q + 5].sum() > 0:
            phi = covered[5 * q:5 * q + 5].sum() / shell[5 * q:5 * q + 5].sum()
            got = hit[inside].mean()
            assert abs(got - phi) < 3 * math.sqrt(phi * (1 - phi) / inside.sum()), (q, got, phi)


@pytest.mark.slow
def test_a_pebble_bed_has_its_first_peak_half_a_diameter_from_the_wall(tmp_path):
    """The pebble-bed scene at N = 300 in radius 3 (about 40 s): the nearest-wall profile is 0 at
    the wall and peaks about 0.5 d inside (the radial porosity profile of packed beds: Mueller
    1992, de Klerk 2003), then dips near 1 d."""
    proc, _, _ = mpipack_run(1, tmp_path, scene="pebble-bed", sets=("n=300", "container.radius=3"), timeout=600)
    assert proc.returncode in (0, 4), describe(proc)
    post_on(1, tmp_path / "out", tmp_path / "post", "density")
    w = json.loads((tmp_path / "post" / "density.json").read_text())["summary"]["container"]["wall_profile"]
    assert w["clip_height"] is not None
    assert 0.3 <= w["first_peak_t_over_d"] <= 0.7 and w["first_peak_phi"] > 0.7
    import csv
    rows = list(csv.DictReader(open(tmp_path / "post" / "density-wall.csv")))
    phi = np.array([float(r["phi"]) for r in rows])
    assert phi[0] < 0.25 and phi[7:13].min() < w["first_peak_phi"] - 0.15


def test_the_centres_first_layer_is_the_touching_one_when_it_splits_on_a_bin_edge():
    """Spheres touching a wall sit at t = d/2, a bin edge: a layer split 1321 / 1371 between the
    bins at 0.45 and 0.55 d is the first layer, not a second layer of 1987 in one bin at 1.35 d
    (a packed bed's counts), and a layer in one bin is at that bin's middle."""
    from mpipack.post.analysis import centres_first_layer
    mid = (np.arange(50) + 0.5) / 10
    first = mid <= 1.5
    counts = np.zeros(50)
    counts[[4, 5, 12, 13]] = [1321, 1371, 218, 1987]
    t = centres_first_layer(mid, counts, first)
    assert t == pytest.approx((0.45 * 1321 + 0.55 * 1371) / 2692) and abs(t - 0.5) < 0.01
    one = np.zeros(50)
    one[[5, 15]] = [100, 100]
    assert centres_first_layer(mid, one, first) == pytest.approx(0.55)
    assert centres_first_layer(mid, np.zeros(50), first) == 0.0
