#!/usr/bin/env bash
# Idempotent set-up for mpipack on Debian/Ubuntu: installs only what is missing.
#   1. apt: Open MPI runtime + headers, parallel HDF5 (libhdf5-openmpi-dev), pkg-config
#   2. .venv at the repo root, with build tools, numpy, numba, mpi4py (built against system MPI)
#   3. h5py built from source against parallel HDF5 (HDF5_MPI=ON); pip's wheel cache makes rebuilds quick
#   4. mpipack in editable mode with its test extras
# Ends by checking that h5py has MPI support; fails loudly otherwise.
set -euo pipefail
top=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$top"
say() { printf '[setup] %s\n' "$*"; }

# ---- 1. system packages ------------------------------------------------------------------
apt_pkgs=(openmpi-bin libopenmpi-dev libhdf5-openmpi-dev pkg-config build-essential)
missing=()
for p in "${apt_pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
py=${PYTHON:-python3}
if ! "$py" -c 'import venv, ensurepip' >/dev/null 2>&1; then
    missing+=(python3-venv python3-dev); py=/usr/bin/python3
fi
if [ ${#missing[@]} -gt 0 ]; then
    say "apt-get install ${missing[*]}"
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
hdf5_dir=$(ls -d /usr/lib/*/hdf5/openmpi 2>/dev/null | head -n 1)
[ -n "$hdf5_dir" ] || { echo "[setup] error: parallel HDF5 not found under /usr/lib/*/hdf5/openmpi" >&2; exit 1; }

# ---- 2. virtual environment --------------------------------------------------------------
if [ ! -x .venv/bin/python ]; then
    say "creating .venv with $py"
    "$py" -m venv .venv
fi
vpy=.venv/bin/python
pipq() { "$vpy" -m pip install --disable-pip-version-check -q "$@"; }
if ! "$vpy" -c 'import setuptools, Cython, pkgconfig, numpy, numba, mpi4py; assert int(setuptools.__version__.split(".")[0]) >= 77' >/dev/null 2>&1; then
    say "installing build tools, numpy, numba, mpi4py (mpi4py compiled against system MPI)"
    pipq -U pip
    pipq -U 'setuptools>=77' 'cython>=3' pkgconfig wheel
    # numba bounds numpy: install them together so the resolver picks a compatible pair.
    pipq numba numpy
    pipq --no-binary=mpi4py mpi4py
fi

# ---- 3. parallel h5py --------------------------------------------------------------------
if ! "$vpy" -c 'import h5py, sys; sys.exit(0 if h5py.get_config().mpi else 1)' >/dev/null 2>&1; then
    say "building h5py against parallel HDF5 in $hdf5_dir (a few minutes the first time)"
    CC=mpicc HDF5_MPI=ON HDF5_DIR="$hdf5_dir" \
        "$vpy" -m pip install --disable-pip-version-check -q --no-binary=h5py --no-build-isolation --force-reinstall --no-deps h5py
fi

# ---- 4. the package ----------------------------------------------------------------------
stamp=.venv/.mpipack-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! "$vpy" -c 'import mpipack' >/dev/null 2>&1; then
    say "installing mpipack (editable) with test extras"
    pipq --no-build-isolation -e '.[test]'
    echo "$want" > "$stamp"
fi

# ---- check -------------------------------------------------------------------------------
if ! "$vpy" -c 'import h5py, sys; sys.exit(0 if h5py.get_config().mpi else 1)'; then
    echo "[setup] FAILED: h5py in .venv was built without MPI support (h5py.get_config().mpi is False)" >&2
    exit 1
fi
say "ok: $("$vpy" -c 'import h5py, mpi4py, numba, numpy; print(f"h5py {h5py.__version__} (mpi), mpi4py {mpi4py.__version__}, numba {numba.__version__}, numpy {numpy.__version__}")')"
