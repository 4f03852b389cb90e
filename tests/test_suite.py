"""``mpipack suite --quick``: the representative subset of the stiff and extreme cases, each a
real ``mpipack run`` under mpirun with a timeout. Every case converges correctly or is detected
(exit 3 or 4) or refused (exit 2) as it allows: never a crash, a hang, or an exit 0 with a
packing that fails the independent check. Known solver findings (reported by the suite, to be
fixed in the solver) may fail their case but must not crash or hang."""

import json
import subprocess
import sys

from conftest import describe, mpi_env

# cases whose failure is a reported finding of the solver, not of the suite (none open now:
# N = 1 is certified, and (4.3) firing on an overlapping configuration exits 4)
KNOWN_FINDINGS = set()


def test_quick_suite(tmp_path):
    out = tmp_path / "suite"
    proc = subprocess.run([sys.executable, "-m", "mpipack.cli", "suite", "--quick", "--out", str(out)],
                          cwd=str(tmp_path), env=mpi_env(), capture_output=True, text=True, timeout=900)
    assert proc.returncode in (0, 1), describe(proc)
    table = (out / "suite.md").read_text()
    assert "| case | expected | outcome | iterations | max overlap | W | exit code | seconds |" in table
    results = json.loads((out / "suite.json").read_text())
    assert len(results) >= 14
    names = {r["case"] for r in results}
    for want in ("N=2 1D NS (analytic)", "one point S (exact)", "N=2 on 3 ranks (empty rank)",
                 "jumps across ranks 3 ranks", "1D chain N=20 NS", "diameters 1:100 N=4000"):
        assert want in names, names
    bad = []
    for r in results:
        assert r["outcome"] not in ("CRASH", "HANG"), r
        if not r["passed"] and r["case"] not in KNOWN_FINDINGS:
            bad.append((r["case"], r["outcome"], r.get("detail")))
    assert not bad, (bad, table)
    # the analytic two-sphere answer and the bitwise rank-count independence were checked
    by = {r["case"]: r for r in results}
    assert by["N=2 1D NS (analytic)"]["outcome"] == "certified"
    assert "bitwise equal to 'N=2 1D NS (analytic)'" in table
    assert "bitwise equal to 'jumps across ranks 1 rank'" in table
    # inside the stable region certified, outside detected
    inside = [r for r in results if r["case"].startswith("N=2 S inside")]
    outside = [r for r in results if r["case"].startswith("N=2 S outside")]
    assert inside and inside[0]["outcome"] == "certified"
    assert outside and outside[0]["outcome"] == "detected"
