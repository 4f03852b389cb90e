"""The nested methods NAP (2.16) and NAV (2.17) in containers and under the point potential and
gravity: the inner kernel's wall terms against a numpy reference of the linearised wall
constraints (2.15), one sphere pulled against a wall and one resting on a floor (their exact
fixed points and wall forces; NAP's undamped orbit on a floor), a small box certified with wall
contacts, the same packing on 1, 2 and 3 ranks in a box and under gravity, and a restart onto
another rank count."""

import zlib

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe, mpipack_run, step_each
from mpipack import config
from mpipack.engine import solver
from mpipack.kernels import daha as kernels
from mpipack.kernels import potential, walls
from mpipack.methods import nested
from mpipack.parallel import exactsum
from mpipack.parallel.comm import Comm

# parameters that certify the boxes below (the paper's N = 100 values of NAP-NS; NAV-NS with a
# lower beta than the paper's 41). NAP has no damping: a W flat along a direction the walls hold
# (gravity; the centre potential's translation in a box) leaves it orbiting (see the floor test)
NAP_NS = ["method.name=nap", "method.form=NS", "method.alpha=0.1", "method.beta=0.16", "method.l_inner=1000"]
NAV_NS = ["method.name=nav", "method.form=NS", "method.alpha=0.31", "method.beta=10.0", "method.tau=0.1",
          "method.l_inner=1000"]
ONE = {"nap": ["method.name=nap", "method.alpha=0.1", "method.beta=0.1"],
       "nav": ["method.name=nav", "method.alpha=0.5", "method.beta=0.1", "method.tau=0.1"]}
BOX = ["n=30", "container.kind=box", "container.lo=[-3.0, -3.0]", "container.hi=[3.0, 3.0]",
       "potential.kind=point", "potential.point=[-1.0, -1.0]"]
GRAVITY_BOX = ["n=40", "container.kind=box", "container.lo=[-3.0, 0.0]", "container.hi=[3.0, 20.0]",
               "potential.kind=gravity"]


# ---------------------------------------------------------------------------------------------
# the inner kernel's walls and potentials against a reference
# ---------------------------------------------------------------------------------------------


def reference_gap(row, x):
    """(s, n) of a centre x (b,) and a wall row, from its definition (``kernels.walls``)."""
    b = x.shape[0]
    if row[0] == walls.PLANE:
        return float(row[1:1 + b] @ x - row[4]), row[1:1 + b].copy()
    v = x - row[1:1 + b]
    if row[0] == walls.CYLINDER:
        v[int(row[5])] = 0.0
    rho = np.linalg.norm(v)
    return row[4] - rho, -v / rho


def reference_walls(form, method, y, xp, diam, wall_rows, wall_lambda, grad_w, p, update):
    """Y^{n+1} and lambda_iw of one inner step with no pairs: phi^p_iw(Y) = c_i (d_i/2 - s^p -
    n^p.(Y_i - X^p_i)), c_i = d_i (S) or 1 (NS), lambda first, then (2.16a) or (2.17a)."""
    cy, cp, cw, cf = nested.nested_coefficients(method, p["alpha"], p["tau"])
    lam = wall_lambda.copy()
    y_new = np.empty_like(y)
    for i in range(y.shape[0]):
        force = np.zeros(y.shape[1])
        c = diam[i] if form == "S" else 1.0
        for w in range(wall_rows.shape[0]):
            s, n = reference_gap(wall_rows[w], xp[i])
            phi = c * (0.5 * diam[i] - s - n @ (y[i] - xp[i]))
            if update:
                lam[i, w] = max(0.0, lam[i, w] + p["beta"] * phi)
            force += lam[i, w] * (-c * n)
        y_new[i] = cy * y[i] + cp * xp[i] - cw * grad_w[i] - cf * force
    return y_new, lam


@pytest.mark.parametrize("update", [True, False], ids=["update", "first"])
@pytest.mark.parametrize("pot", ["point", "gravity"])
@pytest.mark.parametrize("method", ["nap", "nav"])
@pytest.mark.parametrize("form", ["S", "NS"])
def test_inner_kernel_walls_match_reference(form, method, pot, update):
    """3D, a box's six planes, a cylinder's side and a sphere (round walls: the linearisation is
    not the wall), spheres inside, near and beyond them, no pairs."""
    p = {"alpha": 0.3, "beta": 0.4, "tau": 0.2}
    rng = np.random.default_rng(zlib.crc32(f"walls-{form}-{method}-{pot}-{update}".encode()))
    n, b = 30, 3
    box = walls.walls_of(config.load(None, ["dim=3", "n=10", "container.kind=box", "container.lo=[-2, -2, -2]",
                                            "container.hi=[2, 2, 2]"]).container, b)
    round_walls = np.array([[walls.CYLINDER, 0.1, -0.2, 0.0, 2.2, 2.0, 0.0, 0.0],
                            [walls.SPHERE, 0.0, 0.1, 0.2, 2.5, 0.0, 0.0, 0.0]])
    wall_rows = np.vstack([box, round_walls])
    xp = rng.uniform(-2.3, 2.3, size=(n, b))
    y = xp + 0.3 * rng.normal(size=(n, b))
    diam = rng.uniform(0.8, 1.3, size=n)
    shape = (n, wall_rows.shape[0])
    lam0 = np.where(rng.uniform(size=shape) < 0.5, rng.uniform(0.0, 1.0, size=shape), 0.0)
    point = np.array([0.3, -0.4, 0.5])
    if pot == "gravity":
        pvec = np.array([potential.GRAVITY, 1.7, 1.0 / 1.05, -2.0])
        m = (diam / 1.05) ** 3
        grad_w = np.zeros((n, b))
        grad_w[:, 2] = 1.7 * m
    else:
        pvec = np.zeros(4)
        grad_w = (xp if method == "nav" else y) - point
    y_ref, lam_ref = reference_walls(form, method, y, xp, diam, wall_rows, lam0, grad_w, p, update)
    kern = kernels.nested_step(method, form)
    cy, cp, cw, cf = nested.nested_coefficients(method, p["alpha"], p["tau"])
    acc = exactsum.new_accumulator(b + 3)
    maxima = np.zeros(kernels.N_MAX)
    wall_lambda = lam0.copy()
    y_new = np.full_like(y, np.nan)
    offsets = np.zeros(n + 1, dtype=np.int64)
    n_active = kern(y, xp, y_new, n, diam, offsets, np.zeros(0, dtype=np.int32), np.zeros(0), wall_rows,
                    wall_lambda, point, pvec, cy, cp, cw, cf, p["beta"], update, acc, maxima)
    assert np.allclose(y_new, y_ref, rtol=1e-12, atol=1e-12), np.abs(y_new - y_ref).max()
    assert np.allclose(wall_lambda, lam_ref, rtol=1e-12, atol=1e-14)
    if update:  # both branches of max(0, .)
        assert ((lam0 > 0) & (lam_ref == 0)).any() and (lam_ref > lam0).any()
    assert n_active == 2 * np.count_nonzero(lam_ref)
    # the real overlap with a wall at Y^n, in radii
    worst = max(max((0.5 * diam[i] - reference_gap(wall_rows[w], y[i])[0]) / (0.5 * diam[i])
                    for w in range(wall_rows.shape[0])) for i in range(n))
    assert worst > 0 and maxima[kernels.MAX_OVERLAP] == pytest.approx(worst, rel=1e-12)
    if pot == "gravity":  # W / g at Y^n, in the row after the kernel's own sums
        h = (diam / 1.05) ** 3 @ (y[:, 2] + 2.0)
        assert exactsum.value(acc, b + 2) == pytest.approx(h, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# one sphere: the exact fixed points
# ---------------------------------------------------------------------------------------------


@pytest.mark.mpi
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("method", ["nap", "nav"])
def test_one_sphere_pulled_against_a_wall(run_mpipack, method, form):
    """W = |X - P|^2 / 2 with P = (10, 0) beyond the wall x = 5: the minimiser touches the wall,
    X = (5 - d/2, 0), and the wall's force balances the pull: |X - P| = 5.5 (NAV's multiplier
    times tau, the KKT system's)."""
    proc, summary, dump = run_mpipack(1, sets=ONE[method] + ["n=1", f"method.form={form}", "stop.rule=certified",
                                                             "container.kind=box", "container.lo=[-5.0, -5.0]",
                                                             "container.hi=[5.0, 5.0]", "potential.kind=point",
                                                             "potential.point=[10.0, 0.0]"], dump=True)
    assert proc.returncode == 0 and summary["converged"] is True, describe(proc)
    x = dump["x"][0]
    assert abs(x[0] - 4.5) < 1e-4 and abs(x[1]) < 1e-3
    assert summary["W"] == pytest.approx(0.5 * 5.5 ** 2, rel=1e-4)
    import mpipack
    snap = mpipack.read_snapshot(proc.args[proc.args.index("--out") + 1])
    assert snap.fields["wall_force"][0] == pytest.approx(5.5, rel=1e-4)
    assert snap.fields["contacts"][0] == 1


@pytest.mark.mpi
@pytest.mark.parametrize("form", ["S", "NS"])
def test_nav_one_sphere_on_a_floor(run_mpipack, form):
    """W = g m h (m = 1, g = 2): NAV's sphere rests on the floor, h = d/2, which carries its
    weight m g = 2."""
    proc, summary, dump = run_mpipack(1, sets=ONE["nav"] + ["n=1", f"method.form={form}", "stop.rule=certified",
                                                            "container.kind=box", "container.lo=[-5.0, 0.0]",
                                                            "container.hi=[5.0, 10.0]", "potential.kind=gravity",
                                                            "potential.g=2.0"], dump=True)
    assert proc.returncode == 0 and summary["converged"] is True, describe(proc)
    assert abs(dump["x"][0, 1] - 0.5) < 1e-3 and -4.5 <= dump["x"][0, 0] <= 4.5
    assert summary["W"] == pytest.approx(2.0 * 0.5, rel=2e-3)
    import mpipack
    snap = mpipack.read_snapshot(proc.args[proc.args.index("--out") + 1])
    assert snap.fields["wall_force"][0] == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize("form", ["S", "NS"])
def test_nap_one_sphere_on_a_floor_orbits_its_fixed_point(form):
    """NAP has no damping, and gravity's W no curvature: on a plane floor (where (2.15) is the
    constraint itself) NAP is AHA, whose step (h, lambda) -> (h - alpha (m g - lambda),
    lambda + beta (d/2 - h')) has determinant 1. The iterates do not settle: they end on the
    largest orbit about the exact fixed point (h = d/2, lambda = m g = 2) that lambda >= 0
    allows, lambda from 0 to 2 m g, and average to that fixed point."""
    scene = config.load(None, ONE["nap"] + [f"method.form={form}", "n=1", "container.kind=box",
                                            "container.lo=[-5.0, 0.0]", "container.hi=[5.0, 10.0]",
                                            "potential.kind=gravity", "potential.g=2.0"])
    s = solver.Solver(scene, Comm())
    s.initialise()
    floor = walls.wall_names(scene.container, 2).index("-y")
    h, lam = [], []

    def record(fig):
        h.append(s.state.x[0, 1])
        lam.append(s.state.wall_lambda[0, floor])

    step_each(s, 3000, record)  # through the one loop (engine.loop.run), as any user of it
    assert len(h) == 3000
    h, lam = np.array(h[1000:]), np.array(lam[1000:])
    assert h.mean() == pytest.approx(0.5, abs=0.01) and lam.mean() == pytest.approx(2.0, abs=0.01)
    assert lam.min() < 1e-3 and lam.max() > 3.99 and h.max() - h.min() > 3.9


# ---------------------------------------------------------------------------------------------
# packings in a box and under gravity
# ---------------------------------------------------------------------------------------------


def certified_with_walls(summary, dump, sets, out):
    import mpipack
    assert summary["converged"] is True and summary["max_overlap"] <= 1e-3
    scene = config.load(None, sets)
    assert walls.max_outside(dump["x"], scene.n, dump["diam"], walls.walls_of(scene.container, scene.dim)) <= 1e-3
    wall_force = mpipack.read_snapshot(out).fields["wall_force"]
    assert (wall_force > 0).sum() >= 3, wall_force


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["nap-box", "nav-gravity"])
def test_the_same_packing_on_1_2_3_ranks(run_mpipack, case):
    """30 discs in a box pulled to a point off its centre (NAP-NS) and 40 settled under gravity (NAV-NS):
    certified, with spheres pressing on the walls, and the same bits on any rank count."""
    sets = {"nap-box": NAP_NS + BOX, "nav-gravity": NAV_NS + GRAVITY_BOX}[case]
    sets = sets + ["stop.rule=certified", "stop.max_iter=1000"]
    ref = None
    for ranks in (1, 2, 3):
        proc, summary, dump = run_mpipack(ranks, sets=sets, dump=True, tag=f"np{ranks}")
        assert proc.returncode == 0, describe(proc)
        if ref is None:
            certified_with_walls(summary, dump, sets, proc.args[proc.args.index("--out") + 1])
            ref, ref_summary = dump, summary
        else:
            assert_bitwise_equal(ref, dump, f"{case} on {ranks} ranks")
            assert summary["W"] == ref_summary["W"] and summary["iterations"] == ref_summary["iterations"]


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["nap-box", "nav-gravity"])
def test_restart_onto_another_rank_count(tmp_path, case):
    """The walls' multipliers, X^p and NAV's X^{p-1} continue bit for bit: 3 ranks to 30 outer
    iterations, then 2 ranks to 60, against one run of 60 on one rank."""
    sets = {"nap-box": NAP_NS + BOX, "nav-gravity": NAV_NS + GRAVITY_BOX}[case]
    sets = sets + ["stop.rule=eps", "stop.eps=0"]
    for d in ("ref", "run"):
        (tmp_path / d).mkdir()
    p_ref, s_ref, d_ref = mpipack_run(1, tmp_path / "ref", None, sets + ["stop.max_iter=60"], dump=True)
    assert p_ref.returncode == 0, describe(p_ref)
    p1, s1, _ = mpipack_run(3, tmp_path / "run", None, sets + ["stop.max_iter=30", "output.checkpoint_every=30"])
    assert p1.returncode == 0 and s1["checkpoint"]["iteration"] == 30, describe(p1)
    p2, s2, d2 = mpipack_run(2, tmp_path / "run", None, ["stop.max_iter=60"], dump=True,
                             extra=["--restart", tmp_path / "run" / "out"])
    assert p2.returncode == 0 and s2["iterations"] == 60, describe(p2)
    assert_bitwise_equal(d_ref, d2, f"{case}: 3 ranks to 30, then 2 ranks to 60")
    assert s2["W"] == s_ref["W"] and s2["inner_iterations"] == s_ref["inner_iterations"]
