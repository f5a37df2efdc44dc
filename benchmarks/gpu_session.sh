#!/usr/bin/env bash
# The GPU checks of docs/GPU.md, prepared to run as one command on a machine with a GPU (each mode
# fits a 10-minute command; run them one after the other on the same machine where time allows).
#
#   bash benchmarks/gpu_session.sh bench OUT [YARDSTICK]  # --check, the block step at N_G 8192,
#                                                        # a whole cell's busy fraction (~6 min)
#   bash benchmarks/gpu_session.sh campaign OUT          # paper-8192-gpu with --gpus 1 (<= 8 min)
#   bash benchmarks/gpu_session.sh ncu OUT               # Nsight Compute on one launch (~2 min)
#
# OUT receives the JSON, the logs and the GPU's description. YARDSTICK is a folder holding the lean
# FIRE kernel (lean_fire.py) and a jammed packing of 8192 disks (big_8192.npz, arrays x and rad):
# timed beside the block in the same command. The project is installed without its dependencies
# (the GPU machine's image has numba-cuda, h5py, mpi4py and numpy).
set -uo pipefail
mode=${1:?usage: gpu_session.sh bench|campaign|ncu OUT [YARDSTICK]}
out=${2:?usage: gpu_session.sh bench|campaign|ncu OUT [YARDSTICK]}
yard=${3:-}
cd "$(dirname "$0")/.."
mkdir -p "$out"
python3 -m pip install -q --no-deps -e . >"$out/pip.log" 2>&1 || { cat "$out/pip.log"; exit 1; }
export PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR="$PWD/.numba-cache"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv >"$out/gpu.txt" 2>&1
cat "$out/gpu.txt"
case "$mode" in
bench)
    extra=()
    [ -n "$yard" ] && extra=(--baseline "$yard/lean_fire.py" --jammed "$yard/big_8192.npz")
    timeout 560 python3 benchmarks/bench_gpu.py --check --sizes 8192 --threads 512 1024 \
        --registers 64 --batches 1 132 264 --steps 500 --cell 8192:1e-9 --cell-batch 264 \
        "${extra[@]}" --json "$out/bench_gpu.json" 2>&1 | tee "$out/bench_gpu.log"
    ;;
campaign)
    timeout 570 python3 benchmarks/bench_gpu.py --sizes --threads 512 --campaign campaigns/paper-8192-gpu.yaml \
        --json "$out/campaign.json" 2>&1 | tee "$out/campaign.log"
    ;;
ncu)
    timeout 560 ncu --section SpeedOfLight --section Occupancy --section WarpStateStats \
        --section LaunchStats --section MemoryWorkloadAnalysis -k regex:run --launch-skip 2 --launch-count 1 \
        python3 benchmarks/bench_gpu.py --sizes 8192 --threads 512 --registers 64 --batches 132 \
        --steps 200 2>&1 | tee "$out/ncu.log"
    ;;
*)
    echo "gpu_session.sh: unknown mode $mode (bench, campaign or ncu)" >&2
    exit 2
    ;;
esac
