#!/usr/bin/env bash
# One model per real capture for the compaction benchmark: the shipped tiny-synthetic model
# fine-tuned on the capture's own photos at 192x256 (image loss, 1,500 steps of one pair and two
# targets each), with the benchmark's target views left out of the training chunks.
#
#   scripts/capture_models.sh DATA [RUNS]     # DATA holds llff_fern and dtu_scan24
#   python benchmarks/compact.py --checkpoint tiny-synthetic --data DATA \
#       --capture-checkpoint fern=RUNS/capture-fern dtu_scan24=RUNS/capture-dtu_scan24
#
# A model trained only on 64-pixel synthetic rooms reconstructs these photos at 11-14 dB; a loss
# measured against them says little about what compaction keeps. These models are fitted to one
# scene each (their context views included), so they measure compaction on a sharp reconstruction,
# not how the network generalizes. About 40 minutes per capture on one CPU thread.
set -euo pipefail
DATA=${1:?usage: scripts/capture_models.sh DATA [RUNS]}
RUNS=${2:-runs}
STEPS=${STEPS:-1500}
THREADS=${THREADS:-1}

# Chunks of each capture without the benchmark's target views, and its depth bounds (those of the
# benchmark's views, which the benchmark passes to the model).
python - "$DATA" "$RUNS" "$(dirname "$0")/../benchmarks/compact.py" <<'PY'
import importlib.util, sys
from pathlib import Path
import torch
from surfsplat.data.chunks import scene_to_example, write_chunks
from surfsplat.data.load import load_scene

data, runs = Path(sys.argv[1]), Path(sys.argv[2])
spec = importlib.util.spec_from_file_location("compact_benchmark", sys.argv[3])
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
for name, (folder, images, context, target) in bench.REAL.items():
    scene = load_scene(data / folder, images=images)
    keep = [i for i in range(len(scene)) if i not in target]
    out = runs / "capture-chunks" / name
    write_chunks([scene_to_example(scene.select(keep), key=name, image_format="png", timestamps=torch.tensor(keep))], out)
    views = context + target
    bounds = (float(scene.near[views].min()), float(scene.far[views].max()))
    (out / "bounds.txt").write_text(f"{bounds[0]:.4g} {bounds[1]:.4g}\n")  # 4 digits
    print(f"{name}: {len(keep)} of {len(scene)} views, near {bounds[0]:.4f} far {bounds[1]:.4f}")
PY

# Context gaps in frames of the chunk: LLFF frames follow the capture path (the benchmark's pair is
# 3 apart once its targets are gone), DTU's follow the rows of its camera grid (1 apart).
for spec in "fern 2 6" "dtu_scan24 1 4"; do
    set -- $spec
    read -r NEAR FAR < "$RUNS/capture-chunks/$1/bounds.txt"
    surfsplat train --preset tiny --out "$RUNS/capture-$1" --steps "$STEPS" --batch-size 1 --image-shape 192 256 \
        --init-checkpoint tiny-synthetic --dataset chunks --roots "$RUNS/capture-chunks/$1" \
        --set data.near="$NEAR" --set data.far="$FAR" --set data.num_target_views=2 \
        --set data.view_sampler.warm_up_steps=0 \
        --set data.view_sampler.min_distance_between_context_views="$2" \
        --set data.view_sampler.max_distance_between_context_views="$3" \
        --lr 3e-4 --vit-lr 3e-4 --log-every 50 --checkpoint-every 250 --cpu-threads "$THREADS" --no-progress
done
