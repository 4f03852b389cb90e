"""The frontier's scoring (score.score_state, penalty_kkt_residual, best_w, levels_reached)
on hand-built packings and a synthetic trace; frontier.py's merge of per-rank LAMMPS records;
the Recorder on a small LAMMPS run (skipped without the LAMMPS venv). Nothing timed.

    python -m pytest -q tools/peers/test_frontier.py
"""

import math
import os
import subprocess

import numpy as np
import pytest

import frontier
import score

HERE = os.path.dirname(os.path.abspath(__file__))
VENV = os.path.join(HERE, ".venv-lammps")
PY = os.path.join(VENV, "bin", "python")


def test_lammps_venv_is_there_when_required():
    """CI sets MPIPACK_REQUIRE_LAMMPS=1 after tools/peers/setup_lammps.sh: the LAMMPS tests
    here, in test_lammps_fire.py and test_lammps_pebble.py must run there, not skip."""
    if os.environ.get("MPIPACK_REQUIRE_LAMMPS") != "1":
        pytest.skip("MPIPACK_REQUIRE_LAMMPS is not 1 (set by CI)")
    assert os.path.exists(PY), "MPIPACK_REQUIRE_LAMMPS=1 but no LAMMPS venv (bash tools/peers/setup_lammps.sh)"


def _square_packing():
    """4 unit discs on a square of side 0.998 (each touching two, overlap 2e-3 d), one disc
    at the centre-free corner far away: W, overlaps known by hand."""
    x = np.array([[0.0, 0.0], [0.998, 0.0], [0.0, 0.998], [0.998, 0.998], [5.0, 5.0]])
    return x, np.ones(5)


def test_same_positions_same_score_whatever_the_code():
    x, d = _square_packing()
    from_lammps = score.score_state(x.copy(), d, K=100.0)
    from_mpipack = score.score_state(x.copy(), d, kkt=0.25)
    for key in ("max_overlap", "W", "W_over_N2", "density", "contacts_per_sphere"):
        assert from_lammps[key] == from_mpipack[key]
    assert from_lammps["max_overlap"] == pytest.approx(2e-3)
    xbar = x.mean(axis=0)
    assert from_lammps["W"] == pytest.approx(0.5 * ((x - xbar) ** 2).sum())
    assert from_mpipack["kkt"] == 0.25
    assert math.isnan(score.score_state(x, d)["kkt"])
    # the order of the rows does not matter (a code's own ordering, e.g. LAMMPS's ids)
    perm = np.array([3, 0, 4, 2, 1])
    again = score.score_state(x[perm], d[perm], K=100.0)
    assert again["max_overlap"] == from_lammps["max_overlap"]
    assert again["W"] == pytest.approx(from_lammps["W"], rel=1e-15)
    assert again["kkt"] == pytest.approx(from_lammps["kkt"], rel=1e-12)


def test_penalty_kkt_residual_two_discs():
    # discs at -a and +a: the trap pulls each by a towards the centre, the pair pushes each
    # apart by 2 K (1 - 2a); balanced when 2 K (1 - 2a) = a: residual 0
    a = 0.49
    x = np.array([[-a, 0.0], [a, 0.0]])
    K0 = a / (2.0 * (1.0 - 2.0 * a))
    assert score.penalty_kkt_residual(x, 1.0, K0) == pytest.approx(0.0, abs=1e-12)
    # twice as stiff: net force 2 K0 (1 - 2a) * 2 - a = a on each, ||grad W|| = a sqrt 2
    assert score.penalty_kkt_residual(x, 1.0, 2 * K0) == pytest.approx(1.0)
    # no contact: the net force is the trap's pull, the residual 1
    assert score.penalty_kkt_residual(np.array([[-2.0, 0.0], [2.0, 0.0]]), 1.0, 1e6) == pytest.approx(1.0)


def test_penalty_kkt_residual_polydisperse_pair_stiffness():
    # diameters 1 and 2 (d_kl = 1.5, K_kl = K / 2.25): 3D, on the x axis
    x = np.array([[-0.7, 0.0, 0.0], [0.7, 0.0, 0.0]])
    d = np.array([1.0, 2.0])
    K = 3.0
    push = 2.0 * K / 1.5 ** 2 * (1.5 - 1.4)
    net = abs(push - 0.7)
    assert score.penalty_kkt_residual(x, d, K) == pytest.approx(net / 0.7)


def _trace():
    # seconds, max overlap, W, kkt
    rows = [(0.0, 0.3, 80.0, 5.0), (1.0, 2e-3, 90.0, 0.5), (2.0, 9e-4, 112.0, 0.2),
            (3.0, 8e-4, 104.0, 0.05), (4.0, 5e-4, 100.5, 0.02), (5.0, 4e-4, 100.02, 0.008)]
    return [{"seconds": s, "max_overlap": o, "W": w, "kkt": k} for s, o, w, k in rows]


def test_best_w_only_from_states_without_overlap():
    other = [{"seconds": 1.0, "max_overlap": 1e-3, "W": 100.0, "kkt": math.nan},
             {"seconds": 2.0, "max_overlap": 0.2, "W": 10.0, "kkt": 0.0}]
    assert score.best_w([_trace(), other]) == 100.0
    assert score.best_w([[{"seconds": 0.0, "max_overlap": 0.5, "W": 1.0, "kkt": 0.0}]]) is None


def test_levels_reached_on_a_synthetic_trace():
    lv = score.levels_reached(_trace(), 100.0)
    # state 2 (W 112, gap 0.12) is above 1e-1; state 3 (gap 0.04): 1e-1; state 4 (gap 5e-3):
    # 3e-2, 1e-2; state 5 (gap 2e-4): 3e-3 ... 3e-4; the overlapping states never count
    # (state 0: W 80 below W_best; state 1: overlap 2e-3)
    assert lv["W<=0.1"] == 3.0 and lv["W<=0.03"] == 4.0 and lv["W<=0.01"] == 4.0
    assert lv["W<=0.003"] == 5.0 and lv["W<=0.001"] == 5.0 and lv["W<=0.0003"] == 5.0
    assert lv["KKT<=0.1"] == 3.0 and lv["KKT<=0.03"] == 4.0 and lv["KKT<=0.01"] == 5.0
    # a stricter W_best: the finest levels are not reached
    lv = score.levels_reached(_trace(), 99.99)
    assert lv["W<=0.0003"] is None and lv["W<=0.001"] == 5.0
    # NaN residuals (a code that reports none) reach no KKT level
    nan = [dict(s, kkt=math.nan) for s in _trace()]
    assert all(v is None for k, v in score.levels_reached(nan, 100.0).items() if k.startswith("KKT"))
    assert set(lv) == set(frontier.level_keys())


def test_read_lammps_trace_merges_ranks_by_id(tmp_path):
    rng = np.random.default_rng(0)
    n = 7
    xs = [rng.normal(size=(n, 2)) for _ in range(2)]
    owners = [np.array([0, 1, 1, 0, 1, 0, 0]), np.array([1, 1, 0, 0, 0, 1, 0])]
    base = str(tmp_path / "trace.npz")
    for r in range(2):
        tags, rows, counts = [], [], []
        for k in range(2):
            mine = np.flatnonzero(owners[k] == r)[::-1]   # any order
            tags.append(mine + 1)
            rows.append(xs[k][mine])
            counts.append(mine.size)
        np.savez(f"{base[:-4]}.rank{r}.npz", steps=np.array([0, 100]), seconds=np.array([0.0, 1.5 + r]),
                 K=np.array([10.0, 10.0]), counts=np.array(counts), ranks=2, dim=2,
                 tag=np.concatenate(tags), x=np.concatenate(rows))
    recs = frontier.read_lammps_trace(base, 2, np.ones(n))
    assert [r[0] for r in recs] == [0, 100]
    assert [r[1] for r in recs] == [0.0, 1.5]             # rank 0's clock
    for k in range(2):
        np.testing.assert_array_equal(recs[k][3], xs[k])


@pytest.mark.skipif(not os.path.exists(PY), reason="no LAMMPS venv (bash tools/peers/setup_lammps.sh)")
@pytest.mark.parametrize("protocol", ["stiff", "damped"])
def test_recorder_records_every_k_steps(tmp_path, protocol):
    rng = np.random.default_rng(1)
    n = 150
    start = str(tmp_path / "start.npz")
    np.savez(start, x=rng.normal(size=(n, 2)) * 0.5, diam=np.ones(n))
    trace = str(tmp_path / "trace.npz")
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = os.path.join(VENV, "lib")
    p = subprocess.run([PY, os.path.join(HERE, "lammps_fire.py"), start, "--protocol", protocol,
                        "--max-steps", "600", "--check-every", "300", "--trace", trace, "--trace-every", "50",
                        "--json", str(tmp_path / "out.json")], env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode in (0, 4), p.stderr[-2000:]
    recs = frontier.read_lammps_trace(trace, 1, np.ones(n))
    steps = [r[0] for r in recs]
    assert steps[0] == 0 and steps == sorted(set(steps)) and all(s % 50 == 0 for s in steps)
    assert len(steps) >= 600 // 50
    secs = [r[1] for r in recs]
    assert secs == sorted(secs)
    # the records are the run's states: the start first, then states that no longer overlap as much
    d = np.load(start)
    np.testing.assert_allclose(recs[0][3], d["x"], atol=1e-12)
    first, last = score.score_state(recs[0][3], 1.0, K=recs[0][2]), score.score_state(recs[-1][3], 1.0, K=recs[-1][2])
    assert last["max_overlap"] < 0.5 * first["max_overlap"]


def test_a_failed_protocol_is_a_row_of_the_table_not_the_end_of_the_case(tmp_path, monkeypatch):
    # lammps_fire.py ending without its JSON (2D N = 2e5, damped MD, 2 ranks: exit 4 and no
    # result) gives no states and says why; the other codes of the case keep their rows
    monkeypatch.setattr(frontier.subprocess, "run",
                        lambda argv, **kw: subprocess.CompletedProcess(argv, 4, "", "rank 0 gone"))
    args = frontier.argparse.Namespace(trace_every=100, time_limit=10.0, damped_args="")
    states, info = frontier.run_lammps("damped", str(tmp_path / "start.npz"), 2, str(tmp_path), args)
    assert states == [] and info["failed"] == "exit 4" and "rank 0 gone" in info["stderr_tail"]
    result = {"case": {"dim": 2, "n": 6, "ranks": 2, "seed": 1}, "time": "now", "loadavg": (0.5, 0, 0),
              "codes": {"mpipack": {"info": {}, "states": [dict(s, W_over_N2=s["W"] / 36) for s in _trace()]},
                        "damped": {"info": info, "states": states}}}
    frontier.analyse(result)
    assert result["W_best"] == 100.02
    assert all(v is None for v in result["codes"]["damped"]["levels"].values())
    rows = frontier.table(result).splitlines()
    damped = [r for r in rows if r.startswith("| LAMMPS damped")]
    assert len(damped) == 1 and "failed (exit 4)" in damped[0]
    assert any(r.startswith("| mpipack certified") and "| 3.00 |" in r for r in rows)


def test_a_case_where_no_code_reaches_the_overlap_has_a_table():
    # 2D N = 2e5 on 2 ranks: LAMMPS's quench and stiff FIRE ended at overlaps of 0.1 d
    states = [dict(s, max_overlap=0.1, W_over_N2=1.0) for s in _trace()]
    result = {"case": {"dim": 2, "n": 6, "ranks": 2, "seed": 1}, "time": "now", "loadavg": (0.5, 0, 0),
              "codes": {"quench": {"info": {}, "states": states}}}
    frontier.analyse(result)
    assert result["W_best"] is None
    text = frontier.table(result)
    assert "no state within 1e-3 d of overlap" in text
    assert "| LAMMPS FIRE two-stage quench | not reached |" in text


def test_versus_is_mpipack_best_over_lammps_best_per_level():
    # a LAMMPS protocol reaching the coarse levels at 1 s, two mpipack codes at 3 and 5 s
    def trace(t, w, kkt):
        return [{"seconds": t, "max_overlap": 5e-4, "W": w, "kkt": kkt, "W_over_N2": w / 36}]
    result = {"case": {"dim": 2, "n": 6, "ranks": 1, "seed": 1}, "time": "now", "loadavg": (0.5, 0, 0),
              "codes": {"stiff@a": {"info": {}, "states": trace(1.0, 105.0, 0.5)},
                        "jammed@a": {"info": {}, "states": trace(5.0, 100.5, 0.05)},
                        "mpipack@b": {"info": {}, "states": trace(3.0, 100.0, 0.2)}}}
    frontier.analyse(result)
    v = frontier.versus(result)
    assert v["W<=0.1"] == pytest.approx(3.0) and v["W<=0.03"] == "mpipack alone"
    assert v["KKT<=0.1"] == "mpipack alone" and v["KKT<=0.01"] == "neither"
    result["codes"]["stiff@a"]["states"] = []    # a failed protocol reaches nothing
    frontier.analyse(result)
    assert frontier.versus(result)["W<=0.1"] == "mpipack alone"
    assert "| mpipack's best ÷ LAMMPS's best | mpipack alone |" in frontier.table(result)


def test_the_figure_of_a_case_where_no_code_reached_a_level_shows_the_overlaps(tmp_path):
    pytest.importorskip("matplotlib")
    states = [dict(s, max_overlap=0.1 / (1 + s["seconds"]), W_over_N2=1.0) for s in _trace()]
    result = {"case": {"dim": 2, "n": 6, "ranks": 2, "seed": 1}, "time": "now", "loadavg": (0.5, 0, 0),
              "codes": {"quench": {"info": {}, "states": states}, "damped": {"info": {}, "states": []}}}
    frontier.analyse(result)
    png = tmp_path / "empty.png"
    frontier.plot(result, str(png))   # log-scaled seconds of no point at all raised here
    assert png.stat().st_size > 1000
