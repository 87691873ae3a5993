#!/usr/bin/env bash
# The CUDA figures of issues 3-5 in one run, on a machine with an NVIDIA GPU and a Python whose torch
# has CUDA (the project's `.venv` has the CPU wheel). Writes JSON and logs to $OUT (default ./cuda_out).
#
#   DATA=../shared/datasets/lego_200 GT=/work/runs/gt_bench TRAIN_S=120 bash tools/bench/cuda.sh
#
# 1. NeRF training on CUDA (lego_200, PSNR on the 9 held-out views at 30 / 60 / TRAIN_S s).
# 2. extract + cage of that NeRF (the engine's command line).
# 3. Ray-bent vs undeformed render time on CUDA, 200x200 (tools/bench/bending.py --device cuda).
# 4. Point location: the torch path on CUDA beside igl and the CPU kernels (tools/bench/geometry_locate.py).
# 5. Ground-truth deformation benchmark on CUDA, reusing the Cycles ground truth made beforehand on a
#    machine with Blender (GT: a --work folder of tools/bench/bending_groundtruth.py); trains anew.
#
# 0. Kernel launches and host-device syncs per training step and per frame on the CUDA code path
#    (tools/bench/cuda_launches.py; on the CPU it counts the same code path).
# 6. The fox at 1/2 for 60 s, 7. one 1920x1080 lego frame at rest and bent (tools/bench/frame_1080.py).
#
# DEVICE=cpu runs the same steps on the CPU, to check the script before spending GPU time on it
# (TRAIN_S=60 WARM=20 FOX_S=10 REPS=1 EVERY=50 TETS=5000 for a quick dry run: extraction needs a NeRF of a minute
# or more to find a surface).
set -uo pipefail
cd "$(dirname "$0")/../.."  # the repository root
PY=${PY:-python3}
DATA=${DATA:-../shared/datasets/lego_200}
TRAIN_S=${TRAIN_S:-120}
DEVICE=${DEVICE:-cuda}
OUT=${OUT:-cuda_out}
W=${W:-/tmp/nerf_cuda}
mkdir -p "$OUT" "$W"
export PYTHONUNBUFFERED=1
step() { echo "=== $(date +%T) $*"; }

step machine
[ "$DEVICE" = cuda ] && nvidia-smi -L
$PY -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__)"

step "0. launches and syncs of the CUDA code path, on $DEVICE"
$PY tools/bench/cuda_launches.py --device "$DEVICE" --data "$DATA" --warm-steps "${WARM:-300}" --json "$OUT/launches_$DEVICE.json" \
    2>&1 | grep -E '"(launches_mean|launches_max|syncs_mean|syncs_max|launches|syncs|rounds|launches_per_megapixel|syncs_per_round)"'

step "1. train lego on $DEVICE for ${TRAIN_S}s"
$PY tools/bench/nerf_train.py --device "$DEVICE" --data "$DATA" --seconds "$TRAIN_S" --at "30,60,$TRAIN_S" \
    --json "$OUT/train_$DEVICE.json" --save "$W/lego/nerf.ckpt" 2>&1 | tail -n 6

step "2. extract + cage"
$PY -m blender_nerf_deform.engine extract --device "$DEVICE" --nerf "$W/lego/nerf.ckpt" --out "$W/lego/mesh.ply" 2>&1 | tail -n 3
$PY -m blender_nerf_deform.engine cage --nerf "$W/lego/nerf.ckpt" --mesh "$W/lego/mesh.ply" --out "$W/lego/cage.npz" 2>&1 | tail -n 2

step "3. bent vs undeformed render time on $DEVICE"
$PY tools/bench/bending.py --device "$DEVICE" --nerf "$W/lego/nerf.ckpt" --cage "$W/lego/cage.npz" --data "$DATA" \
    --every "${EVERY:-10}" --reps "${REPS:-5}" --json "$OUT/bending_$DEVICE.json" 2>&1 | tail -n 30

step "4. point location (incl. CUDA when DEVICE=cuda)"
CUDA_FLAG=(); [ "$DEVICE" = cuda ] && CUDA_FLAG=(--cuda)
$PY tools/bench/geometry_locate.py --tets "${TETS:-50000}" --repeat 5 "${CUDA_FLAG[@]}" 2>&1 | tail -n 12 | tee "$OUT/locate.txt"

if [ -n "${GT:-}" ]; then
    step "5. ground-truth deformation benchmark on $DEVICE"
    mkdir -p "$W/gt"
    cp -r "$GT"/data "$GT"/gt_* "$W/gt/"  # gt_*: the deformed ground truths and gt_surface_vertices.npy
    $PY tools/bench/bending_groundtruth.py --work "$W/gt" --reuse --device "$DEVICE" --train-seconds "$TRAIN_S" 2>&1 | tail -n 16 | tee "$OUT/groundtruth.txt"
    cp "$W/gt/results.json" "$OUT/groundtruth_$DEVICE.json" 2>/dev/null
fi
step "6. fox at 1/2 on $DEVICE for ${FOX_S:-60}s"
$PY tools/bench/nerf_train.py --device "$DEVICE" --data "${FOX:-../shared/datasets/fox}" --downscale 2 \
    --seconds "${FOX_S:-60}" --at "${FOX_S:-60}" --json "$OUT/fox_$DEVICE.json" 2>&1 | tail -n 4

step "7. a 1920x1080 lego frame, rest and bent"
$PY tools/bench/frame_1080.py --device "$DEVICE" --lego-run "$W/lego" --lego-data "$DATA" --paths fast --reps "${REPS:-2}" \
    --json "$OUT/frame_1080_$DEVICE.json" 2>&1 | tail -n 12
step done
