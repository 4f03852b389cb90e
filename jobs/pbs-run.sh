#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# One mpipack run as one PBS Pro / Torque job, in the run folder OUT/<scene>-<job id>. Before the
# wall time `mpipack run --walltime` checkpoints and exits 5 (at the limit PBS's SIGTERM does the
# same, if the kill delay leaves time to write); submit again with MPIPACK_RUN_DIR to continue
# it, or use jobs/pbs-chain.sh, which does that by itself.
#   qsub -V jobs/pbs-run.sh                        (-V: the settings below may come from the
#   qsub -V -v MPIPACK_RUN_DIR=RUN_DIR jobs/pbs-run.sh      environment as MPIPACK_<NAME>)
# Submit from the mpipack checkout (or set MPIPACK_HOME).
# ---- settings ------------------------------------------------------------------------------
#PBS -N mpipack
#PBS -l select=1:ncpus=4:mpiprocs=4
#PBS -l walltime=01:00:00
#PBS -j oe
# (Torque: #PBS -l nodes=1:ppn=4 instead of select=...)
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file
sets=${MPIPACK_SETS:-}               # --set overrides, space-separated: "n=20000 dim=3"
options=${MPIPACK_OPTIONS:-}         # other mpipack run options: "--seed 3 --dump final.npz"
out=${MPIPACK_OUT:-mpipack-out}      # the run folder: OUT/<scene>-<job id>
limit=${MPIPACK_LIMIT:-01:00:00}     # the job's wall time: as in -l walltime above
margin=${MPIPACK_MARGIN:-60}         # s: mpipack --walltime = the time left at launch - margin
walltime=${MPIPACK_WALLTIME:-}       # or mpipack's --walltime outright, HH:MM:SS
launcher=mpirun                      # reads the nodes from PBS (Open MPI built with tm support)
site_env() {                         # puts mpipack and MPI on PATH on the compute node
    # module load openmpi hdf5/openmpi    # e.g.; see jobs/README.md
    . "$MPIPACK_HOME/tools/env.sh"
}
# ---------------------------------------------------------------------------------------------
set -o pipefail  # (no -u: bash 4.2 of older clusters calls an empty array unbound)
cd "${PBS_O_WORKDIR:-.}" || exit 1
MPIPACK_HOME=${MPIPACK_HOME:-$PWD}
# shellcheck source=jobs/lib.sh
. "$MPIPACK_HOME/jobs/lib.sh"
# shellcheck disable=SC2086  # options: words
mp_args "$scene" $options
site_env
mp_threads
MP_RANKS=$(wc -l < "$PBS_NODEFILE")
job=${PBS_JOBID%%.*}
run_dir=${MPIPACK_RUN_DIR:-$out/$(mp_name "$scene")-$job}
mp_log "job $PBS_JOBID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop $(($(mp_seconds "$limit") - SECONDS))
mp_run "$run_dir" "$walltime"
[ "$MP_CODE" != 5 ] || mp_log "to continue: qsub -V -v MPIPACK_RUN_DIR=$run_dir jobs/pbs-run.sh"
exit "$MP_CODE"
