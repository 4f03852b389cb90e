"""``mpipack paper --quick`` end to end on 2 ranks: the report and its figures are written, and
the numbers in it are the paper's where the quick run can already show it."""

import re
import sys

from conftest import describe, mpirun


def test_paper_quick_report(tmp_path):
    out = tmp_path / "paper"
    proc = mpirun(2, [sys.executable, "-m", "mpipack.cli", "paper", "--quick", "--out", out],
                  cwd=tmp_path, timeout=400)
    assert proc.returncode == 0, describe(proc)
    report = (out / "report.md").read_text()
    for png in ("fig3_iterations_vs_c.png", "fig4_error_vs_iteration_c.png",
                "fig5_error_vs_iteration.png", "fig6_error_vs_iteration.png",
                "fig8_fig10_density_neighbours.png"):
        assert (out / png).stat().st_size > 10000, png
        assert png in report
    # Table 1: 5 methods x 3 tolerances, every start converged
    rows = re.findall(r"^\| (DAHA-NS|DAHA-S|NAP-NS|NAP-S|NAV-NS) \| ([0-9e.-]+) \| (\d+) \| ([0-9.]+) .*\| (\d+)/(\d+) \|$",
                      report, flags=re.M)
    assert len(rows) == 15, report
    for name, eps, t_paper, t_ours, conv, m in rows:
        assert conv == m, (name, eps)
        # the quick run has 5 starts: a factor 2 is far outside any honest noise
        assert 0.5 < float(t_ours) / float(t_paper) < 2.0, (name, eps, t_ours, t_paper)
    # AHA never converges to a packing, DAHA does at N = 7 (Table 2)
    assert re.search(r"^\| AHA-S \| 7 \| no \| no \|", report, flags=re.M)
    assert re.search(r"^\| DAHA-S \| 7 \| yes \| yes \|", report, flags=re.M)
    assert re.search(r"^\| DAHA-NS \| 7 \| yes \| yes \|", report, flags=re.M)
    # 2D density plateau near the paper's 0.87 even at N = 500
    m2 = re.search(r"cloud radius: \*\*([0-9.]+)\*\*", report)
    assert m2 and 0.84 < float(m2.group(1)) < 0.907, report
