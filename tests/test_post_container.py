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
    wall = d.parts["wall"][0]
    # a touching layer's slab average over [0, d/10): pi (t - t^2) integrated, over d/10
    first = math.pi * (0.1 ** 2 / 2 - 0.1 ** 3 / 3) / 0.1
    assert wall["phi"][0] == pytest.approx(first, abs=1e-12)
    assert np.allclose(wall["phi"][:10], wall["phi"][10:20], atol=1e-12)  # layer after layer
    layers = [5, 15, 25, 35, 45]  # each wall's layers at 0.5, 1.5, ... 4.5 d
    assert np.flatnonzero(wall["centres"]).tolist() == layers and set(wall["centres"][layers]) == {6 * m * m}
    assert c["wall_profile"]["centres_first_peak_t_over_d"] == pytest.approx(0.55)
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
    assert {"density.json", "density-axis.csv", "density-wall.csv", "contacts.json"} <= set(got[1])
    assert got[2] == got[1] and got[3] == got[1]
    c = json.loads(got[1]["density.json"])["summary"]["container"]
    full = (math.pi / 6 * diam ** 3).sum()
    assert 0 < full - c["covered"] < 0.2 * full and c["side_walls_cut"] > 0
    assert c["packing_fraction"] == pytest.approx(c["covered"] / (math.pi * 9 * 4), rel=1e-14)
    assert c["axis_profile"]["slabs"] == math.ceil(4 / (diam.mean()) - 1e-9)
    w = json.loads(got[1]["contacts.json"])["summary"]["walls"]
    assert w["by_wall_force"] == int((wf > 0).sum()) and w["mean_wall_force"] == pytest.approx(wf[wf > 0].mean())


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
