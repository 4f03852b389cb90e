"""tools/scaling_fit.py: medians with the uncertified runs counted as the slowest, the
least-squares exponent, the CLI."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))
import scaling_fit  # noqa: E402


def rows_for(dim, law):
    rows = []
    for n in (1000, 4000, 16000):
        for seed, factor in enumerate((0.9, 1.0, 1.1)):
            rows.append({"n": n, "dim": dim, "seed": seed, "converged": True,
                         "iterations": factor * law(n), "seconds": factor * law(n) * n * 1e-6})
        # an uncertified run: counted as the slowest, whatever figures it stopped at
        rows.append({"n": n, "dim": dim, "seed": 9, "converged": False, "iterations": 1.0, "seconds": 1.0})
    return rows


def test_medians_and_exponent():
    rows = rows_for(2, lambda n: 7.0 * n ** 0.5) + rows_for(3, lambda n: 3.0 * n ** 0.8)
    table = scaling_fit.medians(rows)
    assert [e[:3] for e in table[2]] == [(1000, 3, 4), (4000, 3, 4), (16000, 3, 4)]
    # the median of 0.9, 1.0, 1.1 and a run above them all: (1.0 + 1.1) / 2 of the law
    assert table[2][0][3] == pytest.approx(1.05 * 7.0 * 1000 ** 0.5)
    fits = scaling_fit.report(table, 1000, 16000)
    assert fits[2][0] == pytest.approx(0.5) and fits[2][1] == pytest.approx(1.5)
    assert fits[3][0] == pytest.approx(0.8)
    # one size only in the range: no fit
    assert scaling_fit.report(table, 4000, 4000)[2] == (None, None)


def test_cli_writes_the_plot(tmp_path):
    path = tmp_path / "sweep.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows_for(2, lambda n: n ** 0.5)))
    png = tmp_path / "scaling.png"
    proc = subprocess.run([sys.executable, str(TOOLS / "scaling_fit.py"), str(path), "--n-min", "1000",
                           "--png", str(png)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "iterations ~ N^0.50" in proc.stdout and png.stat().st_size > 10000


def test_a_median_on_an_uncertified_run_is_not_given():
    ok = {"n": 100, "dim": 2, "converged": True, "iterations": 500, "seconds": 1.0}
    bad = {"n": 100, "dim": 2, "converged": False, "iterations": 100000, "seconds": 50.0}
    assert scaling_fit.medians([ok, bad, bad])[2] == [(100, 1, 3, None, None)]
    assert scaling_fit.medians([ok, ok, bad])[2] == [(100, 2, 3, 500, 1.0)]
    # two certified, two not: the median's upper half is a failed run
    assert scaling_fit.medians([ok, ok, bad, bad])[2][0][3] is None


def test_the_targets_are_judged_from_the_runs():
    def run(n, its, converged=True, w=0.0693, dim=2):
        return {"n": n, "dim": dim, "converged": converged, "iterations": its, "seconds": 1.0,
                "W_over_N2": w}
    # 2D: iterations ~ N^0.5 from 2000 to 32000, every N = 2000 seed fast and dense enough
    good = [run(2000, 3000), run(2000, 3100), run(8000, 6000), run(32000, 12000)]
    table = scaling_fit.medians(good)
    assert [m for m, _ in scaling_fit.targets(good, table)] == [True, True, True]
    # one N = 2000 seed beyond a third of the paper's 13000 iterations
    slow = good + [run(2000, 4400)]
    assert not scaling_fit.targets(slow, scaling_fit.medians(slow))[-1][0]
    # one N = 2000 seed too loose (W/N^2 above 0.0722)
    loose = good + [run(2000, 3000, w=0.0725)]
    assert not scaling_fit.targets(loose, scaling_fit.medians(loose))[-1][0]
    # an uncertified run anywhere fails the first target; growth like N fails the second
    steep = [run(2000, 2000), run(8000, 8000, converged=False), run(8000, 8000), run(32000, 32000)]
    judged = scaling_fit.targets(steep, scaling_fit.medians(steep))
    assert judged[0][0] is False and "N=8000: 1" in judged[0][1]
    assert judged[1][0] is False and "N^1.00" in judged[1][1]
