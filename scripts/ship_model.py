"""Package a trained checkpoint as a model shipped inside `surfsplat` (loadable by name).

    python scripts/ship_model.py runs/tiny-synthetic-128/checkpoints/step-00001800 \\
        --name tiny-synthetic --eval runs/heldout-eval/metrics.json --command "$(cat recipe.txt)"

Writes `src/surfsplat/model/weights/NAME.safetensors` and `NAME.json`: the weights, the model's
configuration, and metadata (preset, resolution, steps, seed, data, the commands that made it, and
the held-out metrics it scored, from a `surfsplat eval --geometry` metrics.json).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from surfsplat.model.checkpoint import load_checkpoint, save_checkpoint, training_metadata
from surfsplat.model.pretrained import package_file


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="a training checkpoint folder (checkpoints/step-N)")
    parser.add_argument("--name", required=True, help="registry name of the shipped model")
    parser.add_argument("--eval", type=Path, required=True, help="metrics.json of `surfsplat eval --geometry`")
    parser.add_argument("--command", required=True, help="the commands that trained it (recorded verbatim)")
    parser.add_argument("--summary", default=None, help="one line saying how it was trained (the demo quotes it)")
    parser.add_argument("--total-steps", type=int, default=None, help="steps of every stage (default: this run's)")
    args = parser.parse_args()

    model = load_checkpoint(args.checkpoint / "model").eval()
    state = json.loads((args.checkpoint / "train_state.json").read_text())
    run = json.loads((args.checkpoint.parents[1] / "config.json").read_text())
    evaluation = json.loads(args.eval.read_text())
    ((name, scores),) = evaluation["models"].items()
    metadata = training_metadata(int(state["step"]), run) | {
        "seed": run["seed"],
        "data": {
            "dataset": run["data"]["dataset"],
            "synthetic_seed": run["data"]["synthetic_seed"],
            "synthetic_length": run["data"]["synthetic_length"],
            "image_shape": run["data"]["image_shape"],
        },
        "command": args.command,
        **({"summary": args.summary} if args.summary else {}),
        **({"steps": args.total_steps, "final_stage_steps": int(state["step"])} if args.total_steps else {}),
        # The last stage's loss and adapter rules (the closed-surface options among them).
        "recipe": {
            "loss": {k: v for k, v in run["loss"].items() if k.endswith("_weight")},
            "adapter": {
                k: run["model"]["adapter"][k]
                for k in (
                    "tangent_clamp",
                    "tangent_clamp_unit",
                    "multiplier_gradient",
                    "scale_multiplier_range",
                    "scale_floor",
                )
                if k in run["model"]["adapter"]
            },
            "highres": {k: run["data"][k] for k in ("highres_factor", "highres_crop") if k in run["data"]},
            "lr": run["optim"]["lr"],
            "batch_size": run["batch_size"],
        },
        "heldout_metrics": {
            "scenes": scores.get("geometry", {}).get("num_scenes"),
            "hrrc_psnr": {k: v["psnr"] for k, v in scores["mean"].items()},
            "geometry": scores.get("geometry", {}).get("mean"),
            **({"closure": scores["closure"]} if "closure" in scores else {}),
        },
    }
    weights, config = save_checkpoint(model, package_file(args.name), metadata=metadata)
    print(f"wrote {weights} ({weights.stat().st_size / 1e6:.1f} MB) and {config}")


if __name__ == "__main__":
    main()
