"""Build the small test fixtures in this folder from the full sample data and golden fixtures.

Run from the repository root where the full data sits beside it (`../shared`):

    python tests/data/make_fixtures.py [--shared ../shared]

Every reduction is deterministic (fixed seeds, fixed view lists), so running it again rewrites the
same files. What each file is and how it was reduced is listed in `README.md` beside this script.
"""

from __future__ import annotations

import argparse
import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from safetensors import safe_open
from safetensors.torch import save_file

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]

# LLFF fern: the first six views (the chunk tests use context [0, 5] and targets [2, 3, 4]),
# images_8 (504x378) halved by box averaging to 252x189, i.e. 1/16 of the 4032x3024 photos.
FERN_VIEWS = list(range(6))
FERN_FACTOR = 2
# DTU scan 24: adjacent pairs of views four apart (0, 1, 4, 5, ..., 44, 45): the even-numbered ones
# of the reduced list still span the rig's whole arc, so their visual hull predicts the masks of
# their odd-numbered neighbours (every sixth view alone carves a hull too loose for that test);
# images_4 (400x300) box-averaged to 100x75 (1/16 of the 1600x1200 sensor), masks from 1600x1200 too.
DTU_VIEWS = [v for first in range(0, 45, 4) for v in (first, first + 1)]
DTU_FACTOR = 4
# Golden encoder case: a fixed random subset of the 131,072 output rows (Gaussians, ordered by
# view, row, column) and of every compared intermediate's elements.
GOLDEN_ROWS = 1000
GOLDEN_ELEMENTS = 2048
GOLDEN_SEED = 0
SHIFT = 8  # view 1 of the golden input is view 0 shifted 8 px horizontally (checked below)
CROP = 16  # top-left CROP x CROP window of both views, for the adapter's golden test
INTERMEDIATES = [
    "dinov2_input_resized_normalized",
    *[f"dinov2_intermediate_tokens.{i}" for i in range(4)],
    "features_cnn_all_scales.0",
    "features_mv.0",
    "cost_volume",
    "depth_head_logits",
    "mv_upsampler_coarse_invdepth",
    "mv_upsampler_residual_invdepth",
    "gaussian_head_out",
]
OUTPUTS = [
    "gaussians.means",
    "gaussians.covariances",
    "gaussians.harmonics",
    "gaussians.opacities",
    "gaussians.scales_mul",
    "gaussians.normals",
    "visualization_dump.scales",
    "visualization_dump.rotations",
]
# Evaluation indices: the pinned entries the tests look up, plus the first few (null ones kept).
EVAL_KEEP = {
    "evaluation_index_re10k.json": ["5aca87f95a9412c6"],
    "evaluation_index_acid.json": [],
    "evaluation_index_dtu_nctx3.json": [f"scan1_train_{i:02d}" for i in range(4)],
    "dl3dv_start_0_distance_10_ctx_2v_tgt_4v.json": [],
    "evaluation_index_scannet.json": ["scene0707_00_slice00"],
}
EVAL_FIRST = 6
MANIFESTS = ["manifest_small.json", "manifest_vitb_official_base.json", "manifest_vitl_official_large.json"]


def box_downscale(path: Path, factor: int, out: Path) -> None:
    with Image.open(path) as image:
        image.convert("RGB").reduce(factor).save(out, optimize=True)


def make_fern(src: Path, dst: Path) -> None:
    shutil.rmtree(dst, ignore_errors=True)
    folder = dst / f"images_{8 * FERN_FACTOR}"
    folder.mkdir(parents=True)
    names = sorted(p.name for p in (src / "images_8").glob("*.png"))
    for i in FERN_VIEWS:
        box_downscale(src / "images_8" / names[i], FERN_FACTOR, folder / names[i])
    rows = np.load(src / "poses_bounds.npy")[FERN_VIEWS]  # H, W, focal stay those of the full photos
    np.save(dst / "poses_bounds.npy", rows)


def make_dtu(src: Path, dst: Path) -> None:
    shutil.rmtree(dst, ignore_errors=True)
    images, masks = dst / f"images_{4 * DTU_FACTOR}", dst / "mask"
    images.mkdir(parents=True)
    masks.mkdir()
    with np.load(src / "cameras_sphere.npz") as npz:
        cameras = {}
        for new, old in enumerate(DTU_VIEWS):
            cameras[f"world_mat_{new}"] = npz[f"world_mat_{old}"]
            cameras[f"scale_mat_{new}"] = npz[f"scale_mat_{old}"]
    np.savez(dst / "cameras_sphere.npz", **cameras)
    for new, old in enumerate(DTU_VIEWS):
        box_downscale(src / "images_4" / f"{old:06d}.png", DTU_FACTOR, images / f"{new:06d}.png")
        with Image.open(src / "mask" / f"{old:03d}.png") as mask:
            mask.convert("L").reduce(4 * DTU_FACTOR).save(masks / f"{new:03d}.png", optimize=True)


def make_eval_index(src: Path, dst: Path) -> None:
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name, keep in EVAL_KEEP.items():
        full = json.loads((src / name).read_text())
        keys = list(full)[:EVAL_FIRST] + [k for k in keep if k not in list(full)[:EVAL_FIRST]]
        nulls = [k for k in full if full[k] is None][:2]  # excluded entries, when the file has any
        reduced = {k: full[k] for k in keys + [k for k in nulls if k not in keys]}
        lines = [f"{json.dumps(k)}: {json.dumps(v)}" for k, v in reduced.items()]  # one entry a line
        (dst / name).write_text("{\n" + ",\n".join(lines) + "\n}\n")


def make_manifests(src: Path, dst: Path) -> None:
    for name in MANIFESTS:
        full = json.loads((src / name).read_text())
        reduced = {
            "total_parameters": full["total_parameters"],
            "keys": {k: {"shape": v["shape"]} for k, v in full["keys"].items()},
        }
        with gzip.GzipFile(dst / f"{name}.gz", "wb", mtime=0) as f:
            f.write(json.dumps(reduced, separators=(",", ":")).encode())


def _subset(numel: int, count: int, generator: torch.Generator) -> torch.Tensor:
    return torch.randperm(numel, generator=generator)[:count].sort().values.to(torch.int32)


def make_golden(src: Path, dst: Path) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "formula_weights.json", dst / "formula_weights.json")
    make_manifests(src, dst)
    with safe_open(str(src / "case_identity.safetensors"), framework="pt") as f:
        case = {k: f.get_tensor(k) for k in f.keys()}
    image = case["context.image"]  # [1, 2, 3, H, W]
    assert torch.equal(image[0, 1, :, :, :-SHIFT], image[0, 0, :, :, SHIFT:]), "view 1 is no longer a shift of view 0"
    _, V, _, H, W = image.shape
    g = torch.Generator().manual_seed(GOLDEN_SEED)
    out: dict[str, torch.Tensor] = {
        "context.image_view0": image[0, 0].contiguous(),  # [3, H, W]
        "context.image_view1_right": image[0, 1, :, :, -SHIFT:].contiguous(),  # [3, H, SHIFT]
    }
    for k in ("intrinsics", "extrinsics", "near", "far"):
        out[f"context.{k}"] = case[f"context.{k}"]
    # Output rows: the random subset plus every pixel of the top-left crop of both views.
    crop = torch.zeros(V, H, W, dtype=torch.bool)
    crop[:, :CROP, :CROP] = True
    rows = torch.unique(torch.cat([_subset(V * H * W, GOLDEN_ROWS, g), crop.flatten().nonzero()[:, 0].to(torch.int32)]))
    out["rows"] = rows
    out["outputs.depths"] = case["outputs.depths"].reshape(1, -1)[:, rows.long()].contiguous()
    shapes = {"shape.outputs.depths": ",".join(str(s) for s in case["outputs.depths"].shape)}
    for k in OUTPUTS:
        out[f"outputs.{k}"] = case[f"outputs.{k}"][:, rows.long()].contiguous()
        shapes[f"shape.outputs.{k}"] = ",".join(str(s) for s in case[f"outputs.{k}"].shape)
    for k in INTERMEDIATES:
        t = case[f"intermediates.{k}"]
        idx = _subset(t.numel(), GOLDEN_ELEMENTS, g)
        out[f"index.{k}"] = idx
        out[f"intermediates.{k}"] = t.flatten()[idx.long()].contiguous()
        shapes[f"shape.intermediates.{k}"] = ",".join(str(s) for s in t.shape)
    out["crop.gaussian_head_out"] = case["intermediates.gaussian_head_out"][:, :, :CROP, :CROP].contiguous()
    out["crop.depths"] = case["outputs.depths"][:, :, :CROP, :CROP].contiguous()
    meta = {"seed": str(GOLDEN_SEED), "shift": str(SHIFT), "crop": str(CROP), **shapes}
    save_file(out, str(dst / "case_identity_subset.safetensors"), metadata=meta)


def make_lpips(src: Path, dst: Path) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "formula_weights.json", dst / "formula_weights.json")
    with safe_open(str(src / "cases.safetensors"), framework="pt") as f:
        keep = ("a64", "b64", "lpips64", "lpips_same", "ssim64", "psnr64")  # the 256x256 pair stays out
        save_file({k: f.get_tensor(k) for k in keep}, str(dst / "cases64.safetensors"))


def build(shared: Path, out: Path) -> None:
    """Write every reduced fixture under `out` from the full data folder `shared`."""
    make_fern(shared / "data" / "llff_fern", out / "llff_fern")
    make_dtu(shared / "data" / "dtu_scan24", out / "dtu_scan24")
    make_eval_index(shared / "data" / "eval_index", out / "eval_index")
    make_golden(shared / "golden", out / "golden")
    make_lpips(shared / "golden" / "lpips", out / "golden" / "lpips")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared", help="full data folder")
    parser.add_argument("--out", type=Path, default=HERE, help="where to write (default: beside this script)")
    args = parser.parse_args()
    build(args.shared, args.out)
    total = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(f"fixtures in {args.out}: {total / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
