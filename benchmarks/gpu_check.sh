#!/usr/bin/env bash
# The GPU check, as one command on a machine with an NVIDIA GPU and a CUDA build of torch:
#
#   bash benchmarks/gpu_check.sh [SECONDS]        (default 580: the whole script's time budget)
#   STEPS=build_gsplat,cuda_tests bash benchmarks/gpu_check.sh 150       (some steps only)
#
# 1. installs wheels found in .whl/ (gsplat==1.5.3, plyfile, pycolmap; for machines without a
#    registry) into /tmp/site, else expects gsplat importable; installs this repository in place
#    (pip install -e ., no dependencies) so that its plugins are registered;
# 2. builds gsplat's CUDA extension (its first-use JIT build; timed);
# 3. tests/test_raster_gsplat_cuda.py: gsplat on CUDA against the cpu backend, and the hard cases;
# 4. resume_cuda: a short CUDA run with a checkpoint, resumed on CUDA (the model must come back on
#    the GPU);
# 5. benchmarks/reflow_overhead.py whole runs, baseline vs ReFlow, on the GPU (gsplat backend),
#    embedded scene, then (overhead_skating_384) the embedded scene generated at 384x288 (nearer
#    the paper's resolutions, where a step is less bound by kernel launches), then the static
#    scene; 300 + 1000 iterations each.
# Every step has its own time limit inside the budget and the script goes on after a failure;
# logs go to $OUT (or output/gpu_check).
set -u
T0=$(date +%s)
BUDGET=${1:-580}
OUT=${OUT:-output/gpu_check}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16}
STEPS=${STEPS:-build_gsplat,cuda_tests,resume_cuda,overhead_skating,overhead_static,overhead_skating_384}
left() { echo $(( BUDGET - ($(date +%s) - T0) )); }
step() {  # step NAME RESERVE CMD...: run CMD with the time left minus RESERVE seconds
    local name=$1 reserve=$2; shift 2
    [[ ",$STEPS," == *",$name,"* ]] || return 0
    local limit=$(( $(left) - reserve ))
    if (( limit < 20 )); then echo "== $name: skipped (no time left)"; return; fi
    echo "== $name (limit ${limit}s, t=$(( $(date +%s) - T0 ))s)"
    local s=$(date +%s)
    timeout "$limit" "$@" 2>&1 | tee "$OUT/$name.log"
    echo "== $name: exit ${PIPESTATUS[0]} after $(( $(date +%s) - s ))s"
}
source "$(dirname "$0")/gpu_wheels.sh" .whl python3
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . || echo "editable install failed"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch, gsplat, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, 'gsplat', gsplat.__version__, 'cuda', torch.cuda.is_available())"
nproc
step build_gsplat 240 python3 -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat CUDA build failed'; print('gsplat CUDA extension ready')"
step cuda_tests 200 python3 -m pytest -q -p no:cacheprovider tests/test_raster_gsplat_cuda.py -n 2 --tb=short -rA
RESUME_FLAGS="--configs arguments/synthetic/default.py --coarse_iterations 20 --iterations 40 --test_iterations 40 \
  --save_iterations 40 --device cuda --quiet --overwrite"
step resume_cuda 150 bash -c "python3 train.py -m /tmp/resume_a --checkpoint_iterations 30 $RESUME_FLAGS && \
  python3 train.py -m /tmp/resume_b --start_checkpoint /tmp/resume_a/chkpnt_fine_30.pth $RESUME_FLAGS"
step overhead_skating 90 python3 benchmarks/reflow_overhead.py --scene skating --whole-iterations 1000 --iterations 0 \
    --out /tmp/bench_skating --train-flags "--device cuda --backend gsplat"
step overhead_skating_384 60 python3 benchmarks/reflow_overhead.py --scene skating --size 384x288 --whole-iterations 1000 \
    --iterations 0 --out /tmp/bench_skating384 --train-flags "--device cuda --backend gsplat"
step overhead_static 5 python3 benchmarks/reflow_overhead.py --scene static --whole-iterations 1000 --iterations 0 \
    --out /tmp/bench_static --train-flags "--device cuda --backend gsplat"
for f in /tmp/bench_*/whole/*/results.json; do  # the runs' own figures (canonical space timing, flow EPE)
    [ -f "$f" ] && cp "$f" "$OUT/$(basename "$(dirname "$(dirname "$(dirname "$f")")")")_$(basename "$(dirname "$f")")_results.json"
done
for f in /tmp/bench_*/whole/*.json; do [ -f "$f" ] && cp "$f" "$OUT/$(basename "$(dirname "$(dirname "$f")")")_$(basename "$f")"; done
echo "== done at t=$(( $(date +%s) - T0 ))s"
