#!/usr/bin/env bash
# How the shipped `tiny-synthetic` model was made (CPU, one thread each stage; about 55, 80, 50, 70,
# 25, 85 and 45 minutes with a core to itself). Run from the repository root with the package installed.
set -euo pipefail
RUNS=${RUNS:-runs}

# 1. 4000 steps at 64x64 on freshly drawn procedural rooms (batch 4, MSE loss, the tiny preset's
#    one-cycle schedule with peak lr 1e-3).
surfsplat train --preset tiny --out "$RUNS/tiny-synthetic" --steps 4000 --batch-size 4 --image-shape 64 64 \
    --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
    --set data.val_samples=8 --val-every 1000 --log-every 50 --checkpoint-every 250 --no-progress

# 2. 4000 more steps from stage 1 with the rooms' true depth as supervision besides the image loss:
#    relative depth error of the context views (weight 1) and 1 - cos of their normals (weight 0.25),
#    a fresh one-cycle schedule with peak lr 5e-4.
surfsplat train --preset tiny --out "$RUNS/tiny-geo" --steps 4000 --batch-size 4 --image-shape 64 64 \
    --init-checkpoint "$RUNS/tiny-synthetic/checkpoints/step-00004000" --lr 5e-4 --vit-lr 5e-4 \
    --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
    --set loss.depth_weight=1.0 --set loss.normal_weight=0.25 \
    --set data.val_samples=8 --val-every 500 --log-every 50 --checkpoint-every 250 --no-progress

# 3. 2,500 more steps from stage 2 that keep the surface closed (README "Closed surfaces"): the
#    multipliers' clamp passes gradients back into its range, tangents are bounded at 4 pixel
#    footprints, and each target's x4 native truth in a 64-pixel window is supervised (MSE) with a
#    small closure term; the depth and normal terms stay; fresh rooms (seed 11), peak lr 2e-4.
# Stages 3-7 share everything but their length, start, learning rate, rooms, closure weight,
# validation interval and the options after those:
# closed_stage OUT STEPS INIT LR SEED CLOSURE_WEIGHT VAL_EVERY [--set FIELD=VALUE ...].
closed_stage() {
    surfsplat train --preset tiny --out "$1" --steps "$2" --batch-size 4 --image-shape 64 64 \
        --init-checkpoint "$3" --lr "$4" --vit-lr "$4" \
        --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
        --set data.synthetic_seed="$5" --set loss.depth_weight=1.0 --set loss.normal_weight=0.25 \
        --set model.adapter.multiplier_gradient=inward --set model.adapter.tangent_clamp_unit=footprint \
        --set model.adapter.tangent_clamp=4.0 --set data.highres_factor=4 --set data.highres_crop=64 \
        --set loss.highres_weight=1.0 --set loss.closure_weight="$6" \
        --set data.val_samples=8 --val-every "$7" --log-every 50 --checkpoint-every 250 --no-progress "${@:8}"
}
closed_stage "$RUNS/tiny-closed" 2500 "$RUNS/tiny-geo/checkpoints/step-00004000" 2e-4 11 0.01 500

# 4. 4,000 more steps from stage 3 with the closure term at 0.003 (x1 PSNR recovers, the surface
#    stays closed), fresh rooms (seed 12), peak lr 2e-4.
closed_stage "$RUNS/tiny-closed-2" 4000 "$RUNS/tiny-closed/checkpoints/step-00002500" 2e-4 12 0.003 1000

# 5. 1,500 more steps from stage 4 with the closure term at 0.007 (surfels on real photos stay whole:
#    at 0.003 or 0.005 over a third of fern's surfels end under half their footprint), seed 15, peak lr 1e-4.
closed_stage "$RUNS/tiny-closed-3" 1500 "$RUNS/tiny-closed-2/checkpoints/step-00004000" 1e-4 15 0.007 500

# 6. 5,000 more steps from stage 5 at closure weight 0.007 (x1 PSNR and depth improve; fern's surfels
#    shrink again: 64 % under half their footprint), seed 16, peak lr 2e-4.
closed_stage "$RUNS/tiny-closed-4" 5000 "$RUNS/tiny-closed-3/checkpoints/step-00001500" 2e-4 16 0.007 1000

# 7. 2,500 more steps from stage 6 with a scale floor: no tangent scale under half the pixel footprint
#    (fern's surfels had shrunk in stage 6), the closure term at 0.003 and the x4 image term at 0.5
#    (x1 PSNR recovers), seed 21, peak lr 1e-4.
closed_stage "$RUNS/tiny-closed-5" 2500 "$RUNS/tiny-closed-4/checkpoints/step-00005000" 1e-4 21 0.003 500 \
    --set model.adapter.scale_floor=0.5 --set loss.highres_weight=0.5

# 8. Held-out rooms (seed 2026, never trained on) and the evaluation the metadata records.
python - "$RUNS/heldout-64" 64 <<'PY'
import json, sys
from pathlib import Path
from surfsplat.data.synthetic import write_synthetic_chunks
out, size = Path(sys.argv[1]), int(sys.argv[2])
keys = write_synthetic_chunks(out / "chunks", 12, seed=2026, image_shape=(size, size), num_frames=6, supersample=2)
(out / "index.json").write_text(json.dumps({k: {"context": [0, 5], "target": [1, 2, 3, 4]} for k in sorted(keys)}))
PY
CKPT="$RUNS/tiny-closed-5/checkpoints/step-00002500"
surfsplat eval --checkpoint "$CKPT" --data "$RUNS/heldout-64/chunks" --index "$RUNS/heldout-64/index.json" \
    --near 0.5 --far 15 --geometry --out "$RUNS/eval-64" --no-progress

# 9. Into the package, with the commands above and the held-out metrics at the training resolution.
python scripts/ship_model.py "$CKPT" --name tiny-synthetic --eval "$RUNS/eval-64/metrics.json" \
    --total-steps 23500 \
    --summary "the tiny preset trained 4,000 steps with the image loss, then 4,000 with depth and normal supervision, then 15,500 with x4 native-truth supervision and a closure term that keep its surfaces closed (weights 0.01, 0.003, 0.007, 0.007, 0.003), the last 2,500 with surfels at least half a pixel footprint wide, on procedural rooms" \
    --command "scripts/tiny_synthetic.sh: surfsplat train --preset tiny --steps 4000 --batch-size 4 --image-shape 64 64 (fresh rooms every sample, seed 111123); then surfsplat train --steps 4000 --init-checkpoint <stage 1> --lr 5e-4 --set loss.depth_weight=1.0 --set loss.normal_weight=0.25; then surfsplat train --steps 2500 --init-checkpoint <stage 2> --lr 2e-4 --set model.adapter.multiplier_gradient=inward --set model.adapter.tangent_clamp_unit=footprint --set model.adapter.tangent_clamp=4.0 --set data.highres_factor=4 --set data.highres_crop=64 --set loss.highres_weight=1.0 --set loss.closure_weight=0.01 (depth and normal terms kept, rooms of seed 11); then the same for 4000 steps from stage 3 with --lr 2e-4 --set loss.closure_weight=0.003 (rooms of seed 12); then 1500 steps from stage 4 with --lr 1e-4 --set loss.closure_weight=0.007 (rooms of seed 15); then 5000 steps from stage 5 with --lr 2e-4 --set loss.closure_weight=0.007 (rooms of seed 16); then 2500 steps from stage 6 with --lr 1e-4 --set loss.closure_weight=0.003 --set loss.highres_weight=0.5 --set model.adapter.scale_floor=0.5 (rooms of seed 21)"
