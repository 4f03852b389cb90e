#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# One mpipack run as one LSF job, in the run folder OUT/<scene>-<job id>. LSF's warning action
# (SIGUSR1 2 minutes before the run limit, forwarded to mpipack) or `mpipack run --walltime` as
# the backstop makes it checkpoint and exit 5; submit again with MPIPACK_RUN_DIR to continue
# it, or use jobs/lsf-chain.sh, which does that by itself.
#   bsub < jobs/lsf-run.sh          (settings may also come as MPIPACK_<NAME> variables)
#   continue a run: MPIPACK_RUN_DIR=RUN_DIR bsub < jobs/lsf-run.sh
# Submit from the mpipack checkout (or set MPIPACK_HOME).
# ---- settings ------------------------------------------------------------------------------
#BSUB -J mpipack
#BSUB -n 4
#BSUB -R "span[hosts=1]"
#BSUB -W 60
#BSUB -wa USR1
#BSUB -wt 2
#BSUB -o mpipack-%J.out
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file
sets=${MPIPACK_SETS:-}               # --set overrides, space-separated: "n=20000 dim=3"
options=${MPIPACK_OPTIONS:-}         # other mpipack run options: "--seed 3 --dump final.npz"
out=${MPIPACK_OUT:-mpipack-out}      # the run folder: OUT/<scene>-<job id>
limit=${MPIPACK_LIMIT:-01:00:00}     # the job's run limit: as in -W above (minutes there)
margin=${MPIPACK_MARGIN:-60}         # s: mpipack --walltime = the time left at launch - margin
walltime=${MPIPACK_WALLTIME:-}       # or mpipack's --walltime outright, HH:MM:SS
launcher=mpirun                      # reads the hosts from LSF (LSB_DJOB_HOSTFILE)
site_env() {                         # puts mpipack and MPI on PATH on the compute node
    # module load openmpi hdf5/openmpi    # e.g.; see jobs/README.md
    . "$MPIPACK_HOME/tools/env.sh"
}
# ---------------------------------------------------------------------------------------------
set -o pipefail  # (no -u: bash 4.2 of older clusters calls an empty array unbound)
cd "${LS_SUBCWD:-.}" || exit 1
MPIPACK_HOME=${MPIPACK_HOME:-$PWD}
# shellcheck source=jobs/lib.sh
. "$MPIPACK_HOME/jobs/lib.sh"
# shellcheck disable=SC2086  # options: words
mp_args "$scene" $options
site_env
mp_threads
MP_RANKS=${LSB_DJOB_NUMPROC:-1}
run_dir=${MPIPACK_RUN_DIR:-$out/$(mp_name "$scene")-$LSB_JOBID}
mp_log "job $LSB_JOBID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop $(($(mp_seconds "$limit") - SECONDS))
mp_run "$run_dir" "$walltime"
[ "$MP_CODE" != 5 ] || mp_log "to continue: MPIPACK_RUN_DIR=$run_dir bsub < jobs/lsf-run.sh"
exit "$MP_CODE"
