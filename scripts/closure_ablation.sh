#!/usr/bin/env bash
# The cause ablation of README "Closed surfaces": fine-tune the shipped `tiny-synthetic` for the same
# number of steps under one change at a time, then `python benchmarks/closure.py` scores every run on
# the held-out rooms. Each run uses one CPU thread (120 steps: about 5 minutes on an idle core); run the
# variants in parallel where cores allow:
#   scripts/closure_ablation.sh control inward highres nofab footprint all     # RUNS=runs by default
# Every variant keeps the shipped model's last-stage loss (image MSE + depth 1.0 + normals 0.25).
set -euo pipefail
RUNS=${RUNS:-runs}
STEPS=${STEPS:-120}

for variant in "$@"; do
    case "$variant" in
        control) extra=() ;;  # the shipped recipe, continued
        inward) extra=(--set model.adapter.multiplier_gradient=inward) ;;  # stuck multipliers may move back
        highres) extra=(--set model.adapter.multiplier_gradient=inward --set data.highres_factor=4
            --set data.highres_crop=64 --set loss.highres_weight=1.0) ;;  # x4 native truth as well
        nofab) extra=(--set model.adapter.multiplier_gradient=inward
            --set model.adapter.alpha_threshold_train=1.0) ;;  # no pixel reaches tau = 1: no normalisation
        footprint) extra=(--set model.adapter.multiplier_gradient=inward --set model.adapter.tangent_clamp_unit=footprint
            --set model.adapter.tangent_clamp=4.0) ;;  # tangents bounded at 4 pixel footprints
        all) extra=(--set model.adapter.multiplier_gradient=inward --set model.adapter.tangent_clamp_unit=footprint
            --set model.adapter.tangent_clamp=4.0 --set data.highres_factor=4 --set data.highres_crop=64
            --set loss.highres_weight=1.0 --set loss.closure_weight=0.1) ;;
        *) echo "unknown variant $variant (control inward highres nofab footprint all)" >&2; exit 2 ;;
    esac
    surfsplat train --preset tiny --out "$RUNS/ablation-$variant" --steps "$STEPS" --batch-size 4 --image-shape 64 64 \
        --init-checkpoint tiny-synthetic --lr 3e-4 --vit-lr 3e-4 \
        --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
        --set data.synthetic_seed=7 --set loss.depth_weight=1.0 --set loss.normal_weight=0.25 \
        --val-every 0 --log-every 25 --checkpoint-every 60 --no-progress "${extra[@]}"
done
