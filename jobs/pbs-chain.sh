#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# A long run as a chain of PBS Pro / Torque jobs. Each link runs until shortly before its wall
# time (`mpipack run --walltime`), checkpoints and submits the next link (qsub -W
# depend=afterany), which continues from the checkpoint bit for bit -- until the run is
# certified, stops for a reason a new link would not cure (exit 2, 3, 4), is deleted (qdel), or
# max_links is reached. RUN_DIR/chain.log tells the story across links.
#   qsub -V jobs/pbs-chain.sh            (-V: settings may come as MPIPACK_<NAME> variables)
#   continue a stopped chain: qsub -V -v MPIPACK_RUN_DIR=RUN_DIR jobs/pbs-chain.sh
# Submit from the mpipack checkout (or set MPIPACK_HOME).
# ---- settings ------------------------------------------------------------------------------
#PBS -N mpipack-chain
#PBS -l select=1:ncpus=4:mpiprocs=4
#PBS -l walltime=01:00:00
#PBS -j oe
# (Torque: #PBS -l nodes=1:ppn=4 instead of select=...)
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file
sets=${MPIPACK_SETS:-}               # --set overrides, space-separated: "n=20000 dim=3"
options=${MPIPACK_OPTIONS:-}         # other mpipack run options: "--seed 3 --dump final.npz"
out=${MPIPACK_OUT:-mpipack-out}      # the run folder: OUT/<scene>-<first job id>
limit=${MPIPACK_LIMIT:-01:00:00}     # the job's wall time: as in -l walltime above
margin=${MPIPACK_MARGIN:-60}         # s: mpipack --walltime = the time left at launch - margin
walltime=${MPIPACK_WALLTIME:-}       # or mpipack's --walltime outright, HH:MM:SS
max_links=${MPIPACK_MAX_LINKS:-10}   # the most jobs one run may take
script=${MPIPACK_SCRIPT:-jobs/pbs-chain.sh}  # this file (resubmitted), in MPIPACK_HOME or absolute
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
[[ $script = /* ]] || script=$MPIPACK_HOME/$script
# shellcheck disable=SC2086  # options: words
mp_args "$scene" $options
site_env
mp_threads
MP_RANKS=$(wc -l < "$PBS_NODEFILE")
link=${MPIPACK_LINK:-1}
run_dir=${MPIPACK_RUN_DIR:-$out/$(mp_name "$scene")-${PBS_JOBID%%.*}}
mkdir -p "$run_dir"
MP_LOG=$run_dir/chain.log
mp_log "link $link of at most $max_links: job $PBS_JOBID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop $(($(mp_seconds "$limit") - SECONDS))
mp_run "$run_dir" "$walltime"
mp_decide "$link" "$max_links" "$run_dir"
if [ "$MP_NEXT" = 1 ]; then
    if next=$(qsub -V -W depend="afterany:$PBS_JOBID" \
            -v "MPIPACK_RUN_DIR=$run_dir,MPIPACK_LINK=$((link + 1)),MPIPACK_HOME=$MPIPACK_HOME" "$script"); then
        mp_log "link $((link + 1)) submitted: job $next"
        exit 0
    fi
    mp_log "chain ends: qsub failed; to continue, submit again with MPIPACK_RUN_DIR=$run_dir"
fi
exit "$MP_CODE"
