"""A scene runs only what it needs: no h5py or matplotlib without output that needs them, no
ghost exchange on one rank, only the kernels of the chosen method, form and dimension, and the
metrics pass only when asked for (once, at the end, by default). Also: one loop, phase timers.
"""

import subprocess
import sys

import pytest

from conftest import REPO, describe, mpi_env

PROBE = r"""
import sys
from mpipack import cli
from mpipack.kernels import daha as kernels, fire as kernels_fire, lbfgs as kernels_qn
from mpipack.parallel import neighbors
rc = cli.main(["run", "--quiet", "--out", sys.argv[1], "--set", "stop.rule=eps", "--set", "stop.eps=0"]
              + sys.argv[2:])
assert rc == 0, rc
# (numba imports scipy itself when it is installed: post-processing's part of it is scipy.spatial)
heavy = sorted(m for m in ("h5py", "matplotlib", "meshio", "scipy.spatial", "gsd") if m in sys.modules)
compiled = []
for prefix, module in (("", kernels), ("fire:", kernels_fire), ("qn:", kernels_qn), ("nb:", neighbors)):
    for name in dir(module):
        if getattr(getattr(module, name), "signatures", None):  # a numba dispatcher, called
            compiled.append(prefix + name)
print("HEAVY", ",".join(heavy))
print("COMPILED", ",".join(compiled))
"""


def probe(tmp_path, *sets):
    out = tmp_path / "out"
    k = 1
    while out.exists():  # a run never writes into another run's folder
        k += 1
        out = tmp_path / f"out-{k}"
    args = [sys.executable, "-c", PROBE, str(out)]
    for s in sets:
        args += ["--set", s]
    proc = subprocess.run(args, cwd=str(REPO), env=mpi_env(), capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, describe(proc)
    lines = dict(line.split(" ", 1) if " " in line else (line, "") for line in proc.stdout.splitlines())
    return lines["HEAVY"].split(",") if lines["HEAVY"] else [], set(lines["COMPILED"].split(","))


def test_plain_run_imports_no_output_libraries(tmp_path):
    heavy, _ = probe(tmp_path, "n=50", "stop.max_iter=20", "output.snapshots=false")
    assert heavy == [], f"a run without file output imported {heavy}"
    # with its default HDF5 snapshot: h5py, but still no plotting or VTK library
    heavy, _ = probe(tmp_path, "n=50", "stop.max_iter=20")
    assert heavy == ["h5py"], heavy


@pytest.mark.parametrize("sets,want,unwanted", [
    (["dim=3", "method.form=NS", "n=60", "method.schedule=fixed"], {"step_ns3", "metrics_ns", "nb:_build_rows_3"},
     {"step_s1", "step_s2", "step_s3", "step_ns1", "step_ns2", "metrics_s", "nap_s", "nap_ns",
      "nav_s", "nav_ns", "nb:_build_rows_1", "nb:_build_rows_2", "fire:fire_ns3"}),
    # the default schedule: its own kernel, and not DAHA's fixed-parameter one, nor L-BFGS's
    # before its penalty factor reaches the cap
    (["dim=3", "method.form=NS", "n=60"], {"fire:fire_ns3", "metrics_ns", "nb:_build_rows_3"},
     {"step_s3", "step_ns3", "fire:fire_s3", "fire:fire_ns2", "fire:fire_s2", "metrics_s",
      "nb:_build_rows_2", "qn:dots", "qn:direction", "qn:backtrack"}),
    (["method.name=nap", "method.form=S", "n=40", "method.alpha=0.1", "method.beta=0.1"],
     {"nap_s", "metrics_s", "nb:_build_rows_2"},
     {"step_s1", "step_s2", "step_s3", "step_ns1", "step_ns2", "step_ns3", "metrics_ns", "nap_ns",
      "nav_s", "nav_ns", "nb:_build_rows_1", "nb:_build_rows_3"}),
])
def test_only_the_scene_kernels_are_compiled(tmp_path, sets, want, unwanted):
    """numba compiles (or loads from its cache) a function at its first call: a function with
    no signature was never needed. On a cold cache that is what gets compiled."""
    _, compiled = probe(tmp_path, "stop.max_iter=10", *sets)
    assert want <= compiled, (want - compiled, compiled)
    assert not (unwanted & compiled), unwanted & compiled


def test_one_rank_never_exchanges_ghosts(monkeypatch):
    from mpipack.parallel import comm as comm_mod
    from mpipack import config
    from mpipack.engine import loop

    def forbidden(*a, **k):
        raise AssertionError("ghost exchange called on one rank")

    for verb in ("exchange", "borders", "forward", "_send_copies"):
        monkeypatch.setattr(comm_mod, verb, forbidden)
    scene = config.load("paper-2d", ["n=300", "stop.eps=0", "stop.max_iter=200"])
    s, res = loop.run(scene, comm_mod.Comm())
    assert res["rebuilds"] > 1 and res["iterations"] == 200


def test_metrics_pass_runs_only_at_the_end():
    from mpipack import config
    from mpipack.engine import loop, solver
    from mpipack.parallel.comm import Comm
    scene = config.load("paper-2d", ["n=100", "stop.eps=0", "stop.max_iter=100"])
    s = solver.Solver(scene, Comm())
    s.initialise()
    calls = []
    kernel = s.metrics_kernel
    s.metrics_kernel = lambda *a: calls.append(1) or kernel(*a)
    loop.run(scene, s.comm, solver=s)
    assert len(calls) == 1


def test_no_other_module_iterates_the_solver():
    """The loop lives in engine.loop.run: no other source file calls step() (tests included)."""
    offenders = []
    for path in list((REPO / "mpipack").rglob("*.py")) + list((REPO / "tests").rglob("*.py")):
        text = path.read_text()
        if path.name in ("loop.py", "test_footprint.py"):
            continue
        if ".step()" in text:
            offenders.append(str(path.relative_to(REPO)))
    assert offenders == [], offenders


def test_profile_phases_cover_the_loop(run_mpipack):
    for P in (1, 2):
        proc, summary, _ = run_mpipack(P, "paper-2d", ["n=500", "stop.eps=0", "stop.max_iter=400"],
                                       extra=["--profile"])
        assert proc.returncode == 0, describe(proc)
        prof = summary["profile"]
        assert set(prof["phases"]) == {"step", "reduce", "forward", "exchange", "balance",
                                       "borders", "rows", "hooks"}
        assert prof["covered"] >= 0.95, prof
        assert prof["phases"]["step"]["mean"] > 0 and prof["phases"]["rows"]["mean"] > 0
        if P > 1:
            assert prof["phases"]["exchange"]["mean"] > 0 and prof["phases"]["borders"]["mean"] > 0
        assert summary["first_iteration_seconds"] > 0
