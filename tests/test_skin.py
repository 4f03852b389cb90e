"""The adaptive Verlet skin (``neighbor.adaptive_skin``): each build takes the skin that suits
the last period's speed, and the iterates are the same bits whatever skin the rows had."""

import pytest

from conftest import assert_bitwise_equal, describe
from mpipack.engine import rebuild


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
    """A 3D fire-al run to its certificate: the same bits with the skin fixed at 0.3 d and
    chosen per build, on 1, 2 and 3 ranks; the adaptive run's builds went down to the smallest
    skin once the packing had settled (and so were more frequent)."""
    sets = ["dim=3", "n=200"]
    runs = {}
    for adaptive in ("false", "true"):
        proc, summary, dump = run_mpipack(ranks, None, sets + [f"neighbor.adaptive_skin={adaptive}"],
                                          dump=True, extra=["--seed", "2"], timeout=240)
        assert proc.returncode == 0 and dump is not None, describe(proc)
        runs[adaptive] = (summary, dump)
    fixed, adaptive = runs["false"], runs["true"]
    assert_bitwise_equal(fixed[1], adaptive[1], f"adaptive skin on {ranks} ranks")
    assert fixed[0]["iterations"] == adaptive[0]["iterations"]
    assert fixed[0]["skin_range"] == [0.3, 0.3]
    lo, hi = adaptive[0]["skin_range"]
    assert lo == pytest.approx(rebuild.SKIN_MIN) and hi == 0.3
    assert adaptive[0]["rebuilds"] > fixed[0]["rebuilds"]


def test_nested_methods_keep_their_skin(run_mpipack):
    """NAV's inner solves linearise every row entry, so its iterates depend on the rows' reach:
    its skin stays neighbor.skin."""
    proc, summary, _ = run_mpipack(1, "paper-2d", ["n=60", "method.name=nav", "method.form=NS",
                                                   "method.alpha=0.48", "method.beta=126",
                                                   "method.l_inner=10", "method.tau=0.1",
                                                   "stop.max_iter=100"], timeout=120)
    assert proc.returncode in (0, 4), describe(proc)
    assert summary["skin_range"] == [0.3, 0.3]
