# shellcheck shell=bash
# shellcheck disable=SC2034,SC2154  # variables shared with the job script that sources this
# jobs/lib.sh: sourced by the job scripts of jobs/ (Slurm, PBS, LSF), not run on its own. What
# they all do the same way: the run's arguments, one thread per rank, the Numba cache warmed once
# per job, a launch that forwards the scheduler's signals, the exit code, the chain's decision
# and its log. The script sets its settings (scene, sets, launcher, ...) and MP_RANKS first.

# SIGUSR1 before the launch (a job shorter than the signal's lead): not fatal; --walltime stops
# the run in time
trap 'mp_log "SIGUSR1 before the launch: the --walltime backstop will stop the run"' USR1

# ---- the run's arguments -------------------------------------------------------------------
# mp_args [SCENE] [OPTIONS...]: a first argument not starting with "-" is the scene; the rest are
# passed to every `mpipack run` of the job (e.g. --seed 3 --dump final.npz). Sets MP_SETS (the
# --set options of the `sets` setting) and MP_EXTRA.
mp_args() {
    if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then scene=$1; shift; fi
    MP_SETS=()
    local kv
    for kv in $sets; do MP_SETS+=(--set "$kv"); done
    MP_EXTRA=("$@")
}

mp_name() { local b; b=$(basename "$1"); echo "${b%.toml}"; }

# one thread per rank: the ranks are the parallelism; threads would oversubscribe the cores
mp_threads() { export NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1; }

# a time-stamped line on stdout and, when MP_LOG is set, appended to that file
mp_log() {
    local line
    line="$(date '+%Y-%m-%d %H:%M:%S') $*"
    echo "$line"
    if [ -n "${MP_LOG:-}" ]; then echo "$line" >> "$MP_LOG"; fi
}

mp_meaning() {  # what an exit code of mpipack run means
    case $1 in
        0) echo "converged (certified)" ;;
        1) echo "internal error" ;;
        2) echo "bad input" ;;
        3) echo "numerical trouble" ;;
        4) echo "not converged within its bound" ;;
        5) echo "stopped with a checkpoint" ;;
        *) echo "ended by the launcher or a signal" ;;
    esac
}

# [D-]HH:MM:SS, MM:SS or SS -> seconds (nothing for UNLIMITED or anything else)
mp_seconds() {
    local t=$1 d=0 s=0 p parts
    case $t in *-*) d=${t%%-*}; t=${t#*-} ;; esac
    [[ $t =~ ^[0-9]+(:[0-9]+){0,2}$ && $d =~ ^[0-9]+$ ]] || return 0
    IFS=: read -ra parts <<< "$t"
    for p in "${parts[@]}"; do s=$((s * 60 + 10#$p)); done
    echo $((d * 86400 + s))
}
mp_hms() { printf '%02d:%02d:%02d\n' $(($1 / 3600)) $(($1 % 3600 / 60)) $(($1 % 60)); }

# mp_backstop SECONDS_LEFT: mpipack's --walltime, unless the walltime setting gives it: the job's
# time left at launch minus margin (half the time left when that is short); none if unknown
mp_backstop() {
    local left=$1
    if [ -z "$walltime" ] && [ -n "$left" ] && [ "$left" -gt 0 ]; then
        walltime=$(mp_hms $((left > 2 * margin ? left - margin : left / 2)))
    fi
}

# mp_field FILE KEY[.SUBKEY]: a value of a summary.json (empty if absent)
mp_field() {
    python3 - "$1" "$2" <<'PY' 2>/dev/null
import json, sys
v = json.load(open(sys.argv[1]))
for k in sys.argv[2].split("."):
    v = v.get(k) if isinstance(v, dict) else None
print("" if v is None else v)
PY
}

# ---- the Numba cache -----------------------------------------------------------------------
# Numba compiles mpipack's kernels on first use and caches them on disk (in the package's
# __pycache__, or NUMBA_CACHE_DIR). Left to the run, every rank would compile the same kernels
# at the same moment (20-60 s of CPU each, all ranks racing to write the same cache files).
# One small run on 2 ranks of this node compiles everything once -- 2 ranks, because the domain
# decomposition's kernels are never called by 1 rank -- and the ranks then load it in about a
# second. With a warm cache (later links, later jobs) this takes 1-3 s.
mp_warm() {
    local tmp t0=$SECONDS n=2
    tmp=$(mktemp -d "${TMPDIR:-/tmp}/mpipack-warm.XXXXXX")
    [ "${MP_RANKS:-2}" -ge 2 ] || n=1
    # the user's scene at 200 spheres (its dimension and method); the default scene if refused
    if ! launch_few "$n" mpipack run "$scene" "${MP_SETS[@]}" --set n=200 --out "$tmp/a" --quiet \
            > "$tmp/log" 2>&1; then
        launch_few "$n" mpipack run --set n=200 --out "$tmp/b" --quiet >> "$tmp/log" 2>&1
    fi
    mp_log "Numba cache warm ($((SECONDS - t0)) s on $n rank(s))"
    rm -rf "$tmp"
}

# ---- one run (new, or continued from the run folder's checkpoint) ---------------------------
# mp_run RUN_DIR [WALLTIME]: runs mpipack on all ranks with the scheduler's USR1/TERM/INT
# forwarded to the launcher (mpipack then checkpoints and exits 5); sets MP_CODE (mpipack's
# exit code), MP_GOT (the signal received, if any), MP_FROM (iteration restarted from, or 0).
mp_run() {
    local dir=$1 walltime=${2:-} args pid stamp
    mkdir -p "$dir"
    stamp=$dir/.link-start
    touch "$stamp"
    if [ -f "$dir/checkpoint.h5" ]; then
        MP_FROM=$(mp_field "$dir/summary.json" checkpoint.iteration)
        mp_log "restart from the checkpoint of iteration ${MP_FROM:-?} in $dir"
        args=(--restart "$dir" "${MP_SETS[@]}")
    else
        MP_FROM=0
        mp_log "new run of scene $scene${sets:+ (--set $sets)} in $dir"
        args=("$scene" "${MP_SETS[@]}" --out "$dir")
    fi
    [ -z "$walltime" ] || args+=(--walltime "$walltime")
    MP_GOT=""
    mp_launcher "$MP_RANKS"
    mp_log "launch: ${MP_LAUNCH[*]} mpipack run ${args[*]} ${MP_EXTRA[*]}"
    "${MP_LAUNCH[@]}" mpipack run "${args[@]}" "${MP_EXTRA[@]}" &  # $! is the launcher's pid
    pid=$!
    MP_PID=$pid
    trap '_mp_forward USR1 "SIGUSR1: the job nears its limit; asking mpipack to checkpoint"' USR1
    trap '_mp_forward TERM "SIGTERM (scancel, qdel, bkill or the limit): asking mpipack to checkpoint"' TERM
    trap '_mp_forward INT' INT
    wait "$pid"
    MP_CODE=$?
    while kill -0 "$pid" 2>/dev/null; do wait "$pid"; MP_CODE=$?; done  # a signal ended the wait
    trap - TERM INT
    trap : USR1
    # summary.json has mpipack's own code (mpirun reports 1 for ranks that it stopped with
    # SIGTERM after they checkpointed and wrote exit status 5)
    MP_ITER=""
    if [ "$dir/summary.json" -nt "$stamp" ]; then
        local c
        c=$(mp_field "$dir/summary.json" exit_code)
        [ -z "$c" ] || MP_CODE=$c
        MP_ITER=$(mp_field "$dir/summary.json" iterations)
    fi
    rm -f "$stamp"
    mp_log "exit $MP_CODE: $(mp_meaning "$MP_CODE") at iteration ${MP_ITER:-?}"
}

_mp_forward() {  # _mp_forward SIGNAL [MESSAGE]: note it, say it, pass it on to the launcher
    MP_GOT=$1
    [ -z "${2:-}" ] || mp_log "$2"
    kill -"$1" "$MP_PID" 2>/dev/null
}

# ---- the chain's decision ------------------------------------------------------------------
# mp_decide LINK MAX_LINKS RUN_DIR: after mp_run; sets MP_NEXT=1 when a new link should continue
# the run (else 0) and logs why. 0 certified: stop. 5 checkpointed: next, unless SIGTERM asked
# for the stop (scancel, qdel, bkill) or the chain has MAX_LINKS links. 3 numerical trouble and
# 4 not certified at its bound: stop and say so. 2 bad input: stop at once. Others: stop.
mp_decide() {
    local link=$1 max=$2 dir=$3 again="submit again with MPIPACK_RUN_DIR=$3"
    MP_NEXT=0
    case $MP_CODE in
        0) mp_log "chain ends: certified after $link link(s); results in $dir" ;;
        5)
            if [ -n "$MP_GOT" ] && [ "$MP_GOT" != USR1 ]; then
                mp_log "chain ends: stopped by SIG$MP_GOT (cancelled?); checkpoint kept; to continue, $again"
            elif [ "$link" -ge "$max" ]; then
                mp_log "chain ends: $link links reached (max_links); checkpoint kept; to continue, $again"
            else
                MP_NEXT=1
            fi ;;
        3) mp_log "chain ends: numerical trouble, see the job output and $dir/summary.json" \
               "(the last good state is checkpointed)" ;;
        4) mp_log "chain ends: not certified within its bound (stop.max_iter or stop.max_seconds);" \
               "to continue, $again and a larger bound in sets" ;;
        2) mp_log "chain ends: bad input, see the job output" ;;
        *) mp_log "chain ends: exit $MP_CODE, $(mp_meaning "$MP_CODE"), see the job output" ;;
    esac
}

# ---- launchers -----------------------------------------------------------------------------
# mp_launcher N: MP_LAUNCH, the command that starts N ranks (launch_few N CMD... runs it).
# launcher=srun: Slurm starts the ranks itself (PMIx); launcher=mpirun: Open MPI's (or MPICH's)
# mpirun, which reads the nodes from the scheduler (Slurm, PBS's tm, LSF).
mp_launcher() {
    if [ "${launcher:-mpirun}" = srun ]; then MP_LAUNCH=(srun --mpi=pmix -n "$1"); else MP_LAUNCH=(mpirun -n "$1"); fi
}
launch_few() {
    mp_launcher "$1"
    shift
    "${MP_LAUNCH[@]}" "$@"
}
