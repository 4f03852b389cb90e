#!/bin/bash
# Run a scene on a Slurm cluster:  sbatch jobs/slurm.sh [scene] [--set key=value ...]
# Set up once beforehand, from the repository root: bash tools/setup.sh
# (srun needs Slurm's PMIx plugin for Open MPI; where it is missing use: mpirun mpipack run ...)
#SBATCH --job-name=mpipack
#SBATCH --ntasks=4
#SBATCH --time=01:00:00
#SBATCH --output=mpipack-%j.log
set -euo pipefail
cd "${SLURM_SUBMIT_DIR:-.}"
. tools/env.sh
scene=${1:-default}
shift || true
srun mpipack run "$scene" --out "mpipack-out/$(basename "$scene" .toml)-${SLURM_JOB_ID:-local}" "$@"
