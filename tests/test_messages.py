"""What a run says must be true: --quiet keeps the verdict's line; exit 0 without a certificate
does not call itself converged; a certified packing reports its density even where overlaps
within the tolerance take the covered measure above 1."""

import pytest

from conftest import describe, mpipack_run


@pytest.mark.parametrize("ranks", [1, 2])
def test_quiet_keeps_one_verdict_line(tmp_path, ranks):
    proc, s, _ = mpipack_run(ranks, tmp_path, None, ["n=100"])  # quiet
    assert proc.returncode == 0, describe(proc)
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("mpipack: converged (certified) after"), describe(proc)
    assert f"after {s['iterations']} iterations" in lines[0]


def test_the_papers_rule_is_not_called_converged(tmp_path):
    """paper-2d: (4.3) fires at iteration 7332 with the KKT residual at 0.33: exit 0 as the paper
    asks, but the summary's status says what happened."""
    proc, s, _ = mpipack_run(1, tmp_path, "paper-2d", [])
    assert proc.returncode == 0, describe(proc)
    assert s["converged"] is False and s["exit_status"] == "stopped by (4.3), not certified", s["exit_status"]
    assert "NOT certified" in proc.stdout


def test_a_certified_chain_reports_density_one(tmp_path):
    """A 1D chain certified with overlaps of ~3e-6 d covers 1.000001 of its interval: the
    density is 1 to within the tolerance, not 'not reported'."""
    proc, s, _ = mpipack_run(1, tmp_path, None, ["dim=1", "n=20", "seed=0"], quiet=False)
    assert proc.returncode == 0 and s["converged"], describe(proc)
    assert s["density_measured"] > 1.0 and s["density"] == 1.0, s
    assert "packing density 1 to within the overlap tolerance" in proc.stdout, describe(proc)
