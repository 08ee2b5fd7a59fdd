#!/usr/bin/env bash
# How the shipped `tiny-synthetic` model was made (CPU, one thread per run; about 1 h 40 min on a
# 2-core machine). Run from the repository root with the package installed.
set -euo pipefail
RUNS=${RUNS:-runs}

# 1. 4000 steps at 64x64 on freshly drawn procedural rooms (batch 4, MSE loss, the tiny preset's
#    one-cycle schedule with peak lr 1e-3).
surfsplat train --preset tiny --out "$RUNS/tiny-synthetic" --steps 4000 --batch-size 4 --image-shape 64 64 \
    --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
    --set data.val_samples=8 --val-every 1000 --log-every 50 --checkpoint-every 250 --no-progress

# 2. 1800 steps at 128x128 from those weights on other rooms (batch 2, peak lr 3e-4): the cost volume
#    at a quarter of 128 px resolves twice the disparity it does at 64 px.
surfsplat train --preset tiny --out "$RUNS/tiny-synthetic-128" \
    --init-checkpoint "$RUNS/tiny-synthetic/checkpoints/step-00004000/model" \
    --steps 1800 --batch-size 2 --image-shape 128 128 --lr 3e-4 --vit-lr 3e-4 \
    --set data.synthetic_length=100000 --set data.cache_samples=false --set data.synthetic_supersample=2 \
    --set data.synthetic_seed=1 --set data.val_samples=8 --val-every 600 --log-every 50 --checkpoint-every 200 \
    --no-progress

# 3. Held-out rooms (seed 2026, never trained on) and the evaluation the metadata records.
for size in 64 128; do
python - "$RUNS/heldout-$size" "$size" <<'PY'
import json, sys
from pathlib import Path
from surfsplat.data.synthetic import write_synthetic_chunks
out, size = Path(sys.argv[1]), int(sys.argv[2])
keys = write_synthetic_chunks(out / "chunks", 12, seed=2026, image_shape=(size, size), num_frames=6, supersample=2)
(out / "index.json").write_text(json.dumps({k: {"context": [0, 5], "target": [1, 2, 3, 4]} for k in sorted(keys)}))
PY
done
CKPT="$RUNS/tiny-synthetic-128/checkpoints/step-00001800"
for size in 64 128; do
    surfsplat eval --checkpoint "$CKPT" --data "$RUNS/heldout-$size/chunks" --index "$RUNS/heldout-$size/index.json" \
        --near 0.5 --far 15 --geometry --out "$RUNS/eval-$size" --no-progress
done

# 4. Into the package, with the commands above and the held-out metrics at the training resolution.
python scripts/ship_model.py "$CKPT" --name tiny-synthetic --eval "$RUNS/eval-128/metrics.json" \
    --command "scripts/tiny_synthetic.sh (train 4000 steps at 64 px, then 1800 steps at 128 px; seed 111123)"
