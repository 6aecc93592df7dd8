#!/usr/bin/env bash
# The real-capture benchmark's long schedule on a GPU, in calls of under 10 minutes each:
#
#   DATA=/path/to/captures bash benchmarks/gpu_real_suite.sh [suite|convergence] [SECONDS]
#
# suite        benchmarks/real_suite.py at the family configs' own schedule (3000 coarse + 14000
#              fine iterations, arguments/hypernerf/default.py), baseline and ReFlow;
# convergence  benchmarks/convergence.py, fine budgets $BUDGETS (default 1000,3000,7000,14000)
#              with the densification schedule scaled to each budget, $COARSE coarse iterations
#              (default 3000), $JOBS trainings at once (default 1), side-by-side held-out images
#              of each capture's longest budget in OUT/images. Several trainings on one GPU pay
#              little: on an H200 (2026-11-27) 12 at once ran 1.3-1.5 it/s each, about 17 it/s in
#              all, against 13 it/s for one alone (Balloon1 -r 4; the processes' kernels are
#              time-sliced, not overlapped, without MPS). Budget 3000 of basketball at -r 4 (160x90),
#              both methods at once on an H200 (2026-11-27): the baseline 7-8 it/s (300 + 3000 in
#              about 7 minutes), ReFlow 4 it/s beside it and 7 it/s alone (about 10 minutes).
# Every capture at its full stored resolution (-r 1; RESOLUTION=NAME=R,... to change), captures
# $CAPTURES (default nvidia_balloon1,panoptic_basketball; set up with real_suite.py --setup).
# Wheels in $WHEELS (default .whl/: gsplat==1.5.3, plyfile; for machines without a registry) are
# installed into /tmp/site first, the repository in place (its plugins' entry points), and
# gsplat's CUDA extension is built before the clock of the first call starts; the trainings run
# with --backend gsplat (no silent fall-back to the CPU rasterizer).
#
# Each call trains for about SECONDS (default 420) and then stops the run it is in with SIGTERM:
# train.py checkpoints the iteration it is at and exits, and the script exits 3. Call it again
# with the same OUT: it skips the finished runs, continues the stopped one from its checkpoint
# (--start_checkpoint; the trainer's resume is exact: RNG, sampler and optimizer state are in the
# checkpoint) and goes on. Exit 0 = every run done, the table printed and written to OUT; 1 = done
# with failed runs in the table; 2 = an input error (one line). Keep 3 minutes between SECONDS and
# the machine's per-call limit for start-up, the checkpoint, and the final evaluation and renders
# of a run that ends in the call (they are never cut). OUT (default output/gpu_real_<mode>) holds
# the run folders and must survive between calls; the figures of each run are in
# OUT/<capture>/<method>[/fine_<budget>]/results.json, the calls' seconds in real_chunks.json.
set -u
MODE=${1:-suite}
CHUNK=${2:-420}
DATA=${DATA:-data/real}
OUT=${OUT:-output/gpu_real_$MODE}
CAPTURES=${CAPTURES:-nvidia_balloon1,panoptic_basketball}
RESOLUTION=${RESOLUTION:-nvidia_balloon1=1,panoptic_basketball=1}
BUDGETS=${BUDGETS:-1000,3000,7000,14000}
COARSE=${COARSE:-3000}
JOBS=${JOBS:-1}
WHEELS=${WHEELS:-.whl}
PYTHON=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16}
source "$(dirname "$0")/gpu_wheels.sh" "$WHEELS" "$PYTHON"
"$PYTHON" -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null || echo "[gpu_real_suite] editable install failed"
"$PYTHON" - <<'EOF' || exit 2
import torch, sys
if not torch.cuda.is_available():
    sys.exit("error: no CUDA device visible to torch: this script is for a GPU machine (use real_suite.py on the CPU)")
print(f"[gpu_real_suite] {torch.cuda.get_device_name(0)}, torch {torch.__version__}")
import time
start = time.time()
from gsplat.cuda._backend import _C
if _C is None:
    sys.exit("error: gsplat's CUDA extension did not build")
print(f"[gpu_real_suite] gsplat CUDA extension ready ({time.time() - start:.0f} s)")
EOF
case $MODE in
    suite)
        exec "$PYTHON" benchmarks/real_suite.py --captures "$CAPTURES" --data "$DATA" --out "$OUT" \
            --resolution "$RESOLUTION" --coarse_iterations 3000 --iterations 14000 \
            --jobs "$JOBS" --chunk-seconds "$CHUNK" --images "$OUT/images" -- --backend gsplat ;;
    convergence)
        exec "$PYTHON" benchmarks/convergence.py --captures "$CAPTURES" --data "$DATA" --out "$OUT" \
            --resolution "$RESOLUTION" --coarse_iterations "$COARSE" --budgets "$BUDGETS" --jobs "$JOBS" \
            --chunk-seconds "$CHUNK" --plot "$OUT/convergence.png" --images "$OUT/images" -- --backend gsplat ;;
    *)
        echo "error: mode '$MODE': want suite or convergence" >&2
        exit 2 ;;
esac
