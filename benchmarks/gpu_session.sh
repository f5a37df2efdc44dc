#!/usr/bin/env bash
# The GPU checks of docs/GPU.md, prepared to run as one command each on a machine with a GPU (each
# mode fits a 10-minute command; run them one after the other on the same machine where time allows).
#
#   bash benchmarks/gpu_session.sh bench OUT [YARDSTICK]  # --check, the block step at N_G 8192 (512
#                                                        # and 1024 threads, 64 and 128 registers),
#                                                        # the lean kernel, a whole cell (~6 min)
#   bash benchmarks/gpu_session.sh campaign OUT          # paper-8192-gpu with --gpus 1, stop and go
#   bash benchmarks/gpu_session.sh ncu OUT               # Nsight Compute on one launch (~2 min)
#
# OUT receives what each mode measures as it measures it: OUT/MODE.jsonl, one JSON object a line,
# flushed at once (a mode its time limit ends leaves every line written before; the script's own
# lines say how the project was installed, what the GPU is and how the mode ended), OUT/MODE.json
# (the whole record, rewritten after every measurement), OUT/MODE.log, OUT/gpu.txt, OUT/pip.log.
# YARDSTICK is a folder holding the lean FIRE kernel (lean_fire.py) and a jammed packing of 8192
# disks (big_8192.npz, arrays x and rad): timed beside the block in the same command, at 512 threads.
#
# The project is installed without its dependencies and without a build environment (`pip install
# --no-deps --no-build-isolation -e .`: the GPU machine's image has numba-cuda, h5py, mpi4py and
# numpy, and no package index); where that fails (no setuptools >= 64 with wheel, no pip, a
# read-only environment) the script says so and runs the project from the checkout (PYTHONPATH).
#
# Settings (environment):
#   PYTHON                  the interpreter (default python3)
#   GPU_SESSION_LIMIT       seconds a mode's measurement may run (default 530; SIGTERM then, and
#                           SIGKILL 45 s later)
#   GPU_SESSION_STORE       the campaign's store (default OUT/campaign.h5). The campaign mode run
#                           again on the same store goes on from where it stopped: where OUT is new
#                           at every command, name a path that stays (GPU_SESSION_STORE=$PWD/results/x.h5)
#   GPU_SESSION_SPEC        the campaign's spec (default campaigns/paper-8192-gpu.yaml)
#   GPU_SESSION_TIME_LIMIT  the campaign's `campaign run --time-limit` (default GPU_SESSION_LIMIT - 90,
#                           at least half of it)
#   GPU_SESSION_MARGIN      its --margin (default 60; a fifth of a time limit under 300 s)
#   GPU_SESSION_GRACE       its --grace (default 20): after a SIGTERM, the seconds its running
#                           packings get to end before they are abandoned (they start over)
#   GPU_SESSION_BACKEND     bench_gpu.py --backend (auto, cuda, emulate; default auto)
#   GPU_SESSION_INSTALL=0   run from the checkout without installing
#   GPU_SESSION_DRY=1       tiny sizes, every mode in a minute or two: without a GPU under numba's
#                           CUDA simulator (NUMBA_ENABLE_CUDASIM=1) or the emulation
#                           (GPU_SESSION_BACKEND=emulate); tests/test_gpu_session.py runs it
set -uo pipefail
usage="usage: gpu_session.sh bench|campaign|ncu OUT [YARDSTICK]"
mode=${1:?$usage}
out=${2:?$usage}
yard=${3:-}
case "$mode" in bench | campaign | ncu) ;; *)
    echo "gpu_session.sh: unknown mode $mode (bench, campaign or ncu)" >&2
    exit 2
    ;;
esac
mkdir -p "$out" || exit 2
out=$(cd "$out" && pwd)
cd "$(dirname "$0")/.." || exit 2
py=${PYTHON:-python3}
dry=${GPU_SESSION_DRY:-0}
limit=${GPU_SESSION_LIMIT:-530}
jsonl="$out/$mode.jsonl"
log="$out/$mode.log"

say() { echo "gpu_session: $*" | tee -a "$log"; }

note() { # note KIND KEY VALUE ...: one line of OUT/MODE.jsonl from the script itself
    "$py" - "$jsonl" "$mode" "$@" <<'EOF'
import json, sys
path, mode, kind, *kv = sys.argv[1:]
row = {"kind": kind, "mode": mode}
for k, v in zip(kv[::2], kv[1::2]):
    row[k] = int(v) if v.lstrip("-").isdigit() else v
with open(path, "a", encoding="utf-8") as fh:
    fh.write(json.dumps(row) + "\n")
EOF
}

child=
on_signal() {
    say "signal: stopping the $mode mode (what it measured so far is in $jsonl)"
    if [ -n "$child" ]; then
        kill -TERM "$child" 2>/dev/null
    else
        note ended exit 143
        exit 143
    fi
}
trap on_signal TERM INT

# the project: installed in place, or run from the checkout
how=editable
if [ "${GPU_SESSION_INSTALL:-1}" = 0 ]; then
    how="not installed (GPU_SESSION_INSTALL=0)"
elif ! "$py" -m pip install --no-deps --no-build-isolation -e . >"$out/pip.log" 2>&1; then
    how="the editable install failed (its output: $out/pip.log)"
elif [ "$(cd / && "$py" -c 'import campaign, os; print(os.path.dirname(os.path.dirname(campaign.__file__)))' 2>>"$out/pip.log")" != "$PWD" ]; then
    how="installed, but another copy of the project is imported (see $out/pip.log)"
fi
if [ "$how" = editable ]; then
    say "the project is installed in place (pip install --no-deps --no-build-isolation -e .)"
else
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
    say "$how: running the project from the checkout with PYTHONPATH=$PWD"
fi
export PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$PWD/.numba-cache}"
if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv >"$out/gpu.txt" 2>&1
else
    echo "nvidia-smi: not found" >"$out/gpu.txt"
fi
cat "$out/gpu.txt"
note session install "$how" gpu "$(tr '\n' ';' <"$out/gpu.txt")" dry "$dry" python "$("$py" -c 'import sys; print(sys.version.split()[0])')"

measure() { # measure CMD...: CMD under the time limit, its output on the terminal and in OUT/MODE.log
    # (--foreground: CMD stays in this script's process group, so that a signal to the group, a
    # job's end, reaches it; the campaign that bench_gpu.py starts follows it: PR_SET_PDEATHSIG)
    echo "gpu_session: $*" >>"$log"
    timeout --foreground -k 45 "$limit" "$@" > >(tee -a "$log") 2>&1 &
    child=$!
    while :; do # (a signal the trap took ends the wait, not the command: wait again)
        wait "$child"
        rc=$?
        [ "$rc" -gt 128 ] && kill -0 "$child" 2>/dev/null && continue
        break
    done
    child=
    return "$rc"
}

backend=(--backend "${GPU_SESSION_BACKEND:-auto}")
rc=0
case "$mode" in
bench)
    if [ "$dry" = 1 ]; then
        what=(--check --check-cells 16:1e-3 --check-seeds 1 --check-budget 200 --sizes 16 --threads 2
            --registers 64 128 --batches 1 2 --steps 5 --cell 16:1e-3 --cell-batch 1)
        [ -n "$yard" ] && what+=(--baseline "$yard/lean_fire.py" --baseline-steps 3)
    else
        # the defaults: N_G 8192 at 512 and 1024 threads, 64 and 128 registers, 1, 132 and 264 packings
        what=(--check --cell 8192:1e-9 --cell-batch 264)
        [ -n "$yard" ] && what+=(--baseline "$yard/lean_fire.py" --jammed "$yard/big_8192.npz")
    fi
    measure "$py" benchmarks/bench_gpu.py "${backend[@]}" "${what[@]}" --json "$out/bench.json" --jsonl "$jsonl"
    rc=$?
    ;;
campaign)
    store=${GPU_SESSION_STORE:-$out/campaign.h5}
    spec=${GPU_SESSION_SPEC:-campaigns/paper-8192-gpu.yaml}
    tl=${GPU_SESSION_TIME_LIMIT:-$((limit - 90 > limit / 2 ? limit - 90 : limit / 2))}
    margin=${GPU_SESSION_MARGIN:-60}
    if [ -z "${GPU_SESSION_MARGIN:-}" ] && [[ "$tl" =~ ^[0-9]+$ ]] && [ $((tl / 5)) -lt 60 ]; then
        margin=$((tl / 5))
    fi
    poll=30
    if [ "$dry" = 1 ]; then
        poll=2
        if [ -z "${GPU_SESSION_SPEC:-}" ]; then
            spec="$out/dry-campaign.yaml"
            cat >"$spec" <<'EOF'
# gpu_session.sh's dry run: two tiny device: gpu packings
name: gpu-session-dry
seed: 11
grid: {N_G: [16], E_G: [1.0e-3], seeds: 2}
protocol: {device: gpu, gpu_threads: 2}
observables: [scalars]
store: {configurations: false}
EOF
        fi
    fi
    if [ -e "$store" ]; then
        say "the store $store exists: this run goes on from it"
    fi
    measure "$py" benchmarks/bench_gpu.py "${backend[@]}" --sizes --campaign "$spec" --campaign-store "$store" \
        --time-limit "$tl" --margin "$margin" --grace "${GPU_SESSION_GRACE:-20}" --campaign-poll "$poll" \
        --json "$out/campaign.json" --jsonl "$jsonl"
    rc=$?
    ;;
ncu)
    if [ "$dry" = 1 ]; then
        what=(--sizes 16 --threads 2 --registers 64 --batches 2 --steps 5)
    else
        what=(--sizes 8192 --threads 512 --registers 64 --batches 264 --steps 200)
    fi
    app=("$py" benchmarks/bench_gpu.py "${backend[@]}" "${what[@]}" --jsonl "$out/ncu-app.jsonl")
    if command -v ncu >/dev/null; then
        # the third launch: the warm-up and the first timed launch skipped (bench_gpu's time_steps)
        measure ncu --section SpeedOfLight --section Occupancy --section WarpStateStats --section LaunchStats \
            --section MemoryWorkloadAnalysis -k regex:run --launch-skip 2 --launch-count 1 -f -o "$out/ncu" \
            "${app[@]}"
        rc=$?
        if [ -e "$out/ncu.ncu-rep" ]; then
            ncu --import "$out/ncu.ncu-rep" --print-units base | tee -a "$log"
            ncu --import "$out/ncu.ncu-rep" --csv --page details --print-units base >"$out/ncu.csv"
            "$py" - "$out/ncu.csv" "$jsonl" <<'EOF'
import csv, json, sys
with open(sys.argv[1], newline="") as fh, open(sys.argv[2], "a") as out:
    for row in csv.DictReader(fh):
        out.write(json.dumps({"kind": "ncu_metric", **row}) + "\n")
EOF
        else
            say "ncu wrote no report"
            [ "$rc" = 0 ] && rc=1
        fi
    else
        say "ncu (Nsight Compute) is not on the PATH: the ncu mode is skipped"
        note skipped reason "ncu not found"
        if [ "$dry" = 1 ]; then
            say "dry run: the command ncu would profile, run without it"
            measure "${app[@]}"
            rc=$?
        fi
    fi
    ;;
esac
note ended exit "$rc"
say "$mode ended with exit $rc ($jsonl)"
wait
exit "$rc"
