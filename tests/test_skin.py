"""The adaptive Verlet skin (``neighbor.adaptive_skin``): each build takes the skin that suits
the last period's speed, and the iterates are the same bits whatever skin the rows had."""

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe
from mpipack import config
from mpipack.engine import initial as init, rebuild


def test_next_skin_grows_with_the_speed_within_its_bounds():
    d = 1.5
    skins = [rebuild.next_skin(u, d, 0.3 * d) for u in (0.0, 1e-5, 1e-3, 4e-3, 1e-2, 1.0)]
    assert skins[0] == skins[1] == pytest.approx(rebuild.SKIN_MIN * d)
    assert skins[-1] == 0.3 * d
    assert all(a <= b for a, b in zip(skins, skins[1:]))
    assert skins[2] < skins[3] < skins[4] < 0.3 * d
    # s = sqrt(SKIN_COST u d) between the bounds
    assert skins[3] == pytest.approx((rebuild.SKIN_COST * 4e-3 * d) ** 0.5)


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_an_adaptive_skin_changes_no_bit_and_adapts(run_mpipack, ranks):
    """A 3D fire-al run to its certificate: the same bits with the skin fixed at 0.3 d, chosen
    per build below 0.3 d, and chosen per build below the "auto" ceiling (0.6 d in 3D), on 1,
    2 and 3 ranks; the adaptive run's builds went down to the smallest skin once the packing
    had settled (and so were more frequent), the auto ceiling's went above 0.3 d in the fall."""
    sets = ["dim=3", "n=200"]
    runs = {}
    for name, more in (("fixed", ["neighbor.adaptive_skin=false", "neighbor.skin=0.3"]),
                       ("adaptive", ["neighbor.skin=0.3"]), ("auto", [])):
        proc, summary, dump = run_mpipack(ranks, None, sets + more, dump=True, extra=["--seed", "2"],
                                          timeout=240)
        assert proc.returncode == 0 and dump is not None, describe(proc)
        runs[name] = (summary, dump)
    fixed, adaptive, auto = runs["fixed"], runs["adaptive"], runs["auto"]
    assert_bitwise_equal(fixed[1], adaptive[1], f"adaptive skin on {ranks} ranks")
    assert_bitwise_equal(fixed[1], auto[1], f"adaptive skin, auto ceiling, on {ranks} ranks")
    assert fixed[0]["iterations"] == adaptive[0]["iterations"] == auto[0]["iterations"]
    assert fixed[0]["skin_range"] == [0.3, 0.3]
    lo, hi = adaptive[0]["skin_range"]
    assert lo == pytest.approx(rebuild.SKIN_MIN) and hi == 0.3
    assert adaptive[0]["rebuilds"] > fixed[0]["rebuilds"]
    lo, hi = auto[0]["skin_range"]
    assert lo == pytest.approx(rebuild.SKIN_MIN) and 0.3 < hi <= config.SKIN_AUTO_FIRE_AL_3D
    assert auto[0]["rebuilds"] < adaptive[0]["rebuilds"]


def test_nested_methods_keep_their_skin(run_mpipack):
    """NAV's inner solves linearise every row entry, so its iterates depend on the rows' reach:
    its skin stays neighbor.skin."""
    proc, summary, _ = run_mpipack(1, "paper-2d", ["n=60", "method.name=nav", "method.form=NS",
                                                   "method.alpha=0.48", "method.beta=126",
                                                   "method.l_inner=10", "method.tau=0.1",
                                                   "stop.max_iter=100"], timeout=120)
    assert proc.returncode in (0, 4), describe(proc)
    assert summary["skin_range"] == [0.3, 0.3]


def _first_rows(scene):
    """A solver set up on ``scene`` (one rank, in-process): its start's rows and skin."""
    from mpipack.engine.solver import Solver
    from mpipack.parallel.comm import Comm
    s = Solver(scene, Comm())
    s.initialise()
    st = s.state
    n = st.n_local
    owner = np.repeat(np.arange(n), np.diff(st.pair_offsets[:n + 1]))
    gap = np.linalg.norm(st.x[owner] - st.x[st.pair_j[:st.pair_offsets[n]]], axis=1) \
        - 0.5 * (st.diam[owner] + st.diam[st.pair_j[:st.pair_offsets[n]]])
    return s, gap


@pytest.mark.parametrize("dim", [2, 3])
def test_a_dense_start_is_built_with_a_small_skin_and_no_bit_changes(dim, monkeypatch):
    """A dense fresh start's first rows take a small skin (init.DENSE_START_SKIN: its rows at
    the usual skin are the run's largest); the build after the spread takes the usual skin; and
    the run is the same bits as one whose start is built with the usual skin."""
    from mpipack import config
    from mpipack.engine import loop
    from mpipack.engine.solver import Solver
    from mpipack.parallel.comm import Comm
    scene = config.load("default", [f"dim={dim}", "n=400", "stop.max_iter=600"])
    s, gap = _first_rows(scene)
    assert s.skin == init.DENSE_START_SKIN * s.d_max and gap.size > 10 * 400  # tens of contacts a sphere
    assert np.all(gap < s.skin)
    built = s.counters["rebuilds"]
    # two iterations: the first pass (moving the spheres by ~1e-3 d) needs no build; the spread does
    loop.run(config.load("default", [f"dim={dim}", "n=400", "stop.max_iter=2"]), Comm(), solver=s)
    assert s.skin == s.skin_max and s.counters["rebuilds"] == built + 1
    solver_new, res_new = loop.run(scene, Comm())

    usual = Solver.rebuild
    monkeypatch.setattr(Solver, "rebuild", lambda self, rebalance=False, hist=None, skin=None:
                        usual(self, rebalance, hist))
    s_usual, gap_usual = _first_rows(scene)
    assert s_usual.skin == s_usual.skin_max > 0.0 and gap_usual.size > gap.size
    assert np.any(gap_usual > init.DENSE_START_SKIN * s_usual.d_max)  # the usual skin reaches further
    solver_old, res_old = loop.run(scene, Comm())
    new, old = solver_new.gather(), solver_old.gather()
    assert res_new["iterations"] == res_old["iterations"]
    for key in ("x", "x_prev", "pairs_gid", "pairs_lambda"):
        assert np.array_equal(new[key].view(np.uint8), old[key].view(np.uint8)), key
    assert res_new["skin_min"] == res_old["skin_min"]  # the start's build is not in the skin range


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_a_packed_start_keeps_the_usual_skin(dim):
    """A lattice start (a packing: it fills its cloud's volume about once) is built with the
    usual skin, so that a still start is not built again; a dense Gaussian one with
    init.DENSE_START_SKIN."""
    from mpipack import config
    lattice = config.load("default", [f"dim={dim}", "n=300", "init.kind=lattice"])
    s, gap = _first_rows(lattice)
    assert s.skin == s.skin_max > 0.0 and np.any(gap >= 0.0)
    dense = config.load("default", [f"dim={dim}", "n=300"])
    s_dense, gap_dense = _first_rows(dense)
    assert s_dense.skin == init.DENSE_START_SKIN * s_dense.d_max < s_dense.skin_max
    # ``mpipack check`` counts the rows the run builds: the same skin, about as many entries
    from mpipack.analysis import footprint
    assert footprint.start_skin(lattice) == s.skin / s.d_max
    assert footprint.start_skin(dense) == s_dense.skin / s_dense.d_max
    estimate = 2 * footprint.start_and_memory(dense, 1, budget_bytes=2 ** 40)["row_pairs"]
    assert 0.67 < estimate / gap_dense.size < 1.5, (estimate, gap_dense.size)


def test_a_run_that_stops_at_its_dense_start_writes_a_plain_summary(run_mpipack):
    """stop.max_iter = 0 on a dense start: only the start's build was made, which the skin range
    leaves out; summary.json has no skin range rather than an infinite one."""
    proc, summary, _ = run_mpipack(1, None, ["n=200", "stop.max_iter=0"], timeout=120)
    assert proc.returncode in (0, 4), describe(proc)
    assert summary["rebuilds"] == 1 and "skin_range" not in summary, summary.get("skin_range")
