"""Hand cases for score.py (run: python -m pytest -q tools/peers/test_score.py)."""

import math

import numpy as np
import pytest

import score


def test_two_discs_overlapping():
    x = np.array([[0.0, 0.0], [0.9, 0.0]])
    f = score.score(x, np.ones(2))
    assert f["max_overlap"] == pytest.approx(0.1)
    assert f["W"] == pytest.approx(0.5 * 2 * 0.45 ** 2)        # = 1/(2N) |X_1 - X_2|^2
    assert f["W_over_N2"] == pytest.approx(0.2025 / 4)
    assert f["radius_of_gyration"] == pytest.approx(0.45)
    assert f["contacts"] == 1 and f["overlapping_pairs"] == 1
    # each disc (radius 0.5, centre at 0.45) meets the ball B(0, 0.45) in a lens
    s, a, R = 0.45, 0.5, 0.45
    lens = (a * a * math.acos((s * s + a * a - R * R) / (2 * s * a))
            + R * R * math.acos((s * s + R * R - a * a) / (2 * s * R))
            - 0.5 * math.sqrt((-s + a + R) * (s + a - R) * (s - a + R) * (s + a + R)))
    assert f["density"] == pytest.approx(2 * lens / (math.pi * R * R))


def test_three_spheres_3d_polydisperse():
    # sphere 1 (d = 2) touches sphere 0 (d = 1): d_01 = 1.5 = r; sphere 2 (d = 1) is pressed
    # into sphere 0 by 2e-3 (overlap 2e-3 d); spheres 1 and 2 are apart (r = 1.80 > 1.5)
    x = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 0.998, 0.0]])
    f = score.score(x, np.array([1.0, 2.0, 1.0]))
    assert f["max_overlap"] == pytest.approx(2e-3)
    assert f["contacts"] == 2
    assert f["overlapping_pairs"] == 1
    xbar = x.mean(axis=0)
    assert f["W"] == pytest.approx(0.5 * ((x - xbar) ** 2).sum())
    pair_sum = sum(((x[i] - x[j]) ** 2).sum() for i in range(3) for j in range(i + 1, 3))
    assert f["W"] == pytest.approx(pair_sum / (2 * 3))


def test_contact_tolerance_and_no_overlap():
    x = np.array([[0.0], [1.0015], [2.0040]])          # 1D chain: gaps 1.5e-3 and 2.5e-3
    f = score.score(x, np.ones(3))
    assert f["max_overlap"] == 0.0
    assert f["contacts"] == 1                           # r < d (1 + 2e-3) for the first gap only


@pytest.mark.parametrize("dim, expected", [
    (2, 2 * math.pi / 3 - math.sqrt(3) / 2),             # lens of two unit discs at distance 1
    (3, math.pi * (4 + 1) * (2 - 1) ** 2 / 12),          # lens of two unit balls at distance 1
])
def test_lens_measures(dim, expected):
    assert score.intersection_measure(dim, np.array([1.0]), np.array([1.0]), 1.0)[0] == pytest.approx(expected)
    # a ball well inside counts whole, one far outside not at all
    inside = score.intersection_measure(dim, np.array([0.2]), np.array([0.5]), 1.0)[0]
    assert inside == pytest.approx(score.ball_measure(dim, 0.5))
    assert score.intersection_measure(dim, np.array([1.6]), np.array([0.5]), 1.0)[0] == 0.0


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_cell_list_matches_brute_force(dim):
    rng = np.random.default_rng(dim)
    x = rng.normal(size=(300, dim)) * 3
    i, j = score._pairs_cells(x, 1.0)
    got = set(zip(i.tolist(), j.tolist()))
    d = np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1))
    want = {(a, b) for a, b in zip(*np.nonzero(d < 1.0)) if a < b}
    assert got == want
    ci, cj = score.close_pairs(x, 1.0)
    assert set(zip(ci.tolist(), cj.tolist())) == want


def test_settled_lookback():
    steps = [100, 200, 300, 400, 500, 600]
    # not enough checks in the last third of 600 steps (cut at 400: 400, 500, 600 = 2 intervals)
    assert not score.settled(steps, [1.0] * 6)
    steps = [100 * k for k in range(1, 11)]             # cut at 667: look-back from step 600
    W = [9, 8, 7, 6, 5, 1.004, 0.999, 1.0, 1.0, 1.0]
    assert score.settled(steps, W)
    W[5] = 1.02                                       # step 600 is in the look-back: not settled
    assert not score.settled(steps, W)
    # a model change restarts the list: the look-back must lie inside the new stage
    assert not score.settled([900, 1000, 1100, 1200], [1.0] * 4)
    assert score.settled([900, 1000, 1100, 1200, 1300, 1400], [1.0] * 6)
    assert score.at_finish_line({"max_overlap": 1e-3}, steps, [1.0] * 10)
    assert not score.at_finish_line({"max_overlap": 1.1e-3}, steps, [1.0] * 10)
