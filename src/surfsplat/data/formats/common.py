"""Helpers shared by the format readers: validated cameras and same-size image stacks."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from ...geometry.cameras import Cameras, validate_c2w, validate_intrinsics
from ...utils.checks import SurfSplatInputError
from ..images import read_image, read_image_size
from ..posed_images import check_finite_rows


def make_cameras(c2w: Tensor, K: Tensor, source: str, dtype: torch.dtype) -> Cameras:
    """Validated cameras whose errors name the source file: c2w [N, 4, 4], K [N, 3, 3]."""
    check_finite_rows(c2w, source, "camera")
    check_finite_rows(K, source, "intrinsics of camera")
    validate_c2w(f"{source}: camera", c2w.double())
    validate_intrinsics(f"{source}: intrinsics of camera", K.double())
    return Cameras(c2w.to(dtype), K.to(dtype), validate=False)


def pick_image_folder(root: Path, images: str | None, names: tuple[str, ...], where: str) -> Path:
    """The image folder of a capture: `images` when given, else the first of `names` under root,
    else the single `images_N` folder (a downsampled copy). `where` ends the not-found message."""
    if images is not None:
        folder = root / images
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: image folder not found")
        return folder
    for name in names:
        if (root / name).is_dir():
            return root / name
    candidates = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("images_"))
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        quoted = [f"'{n}'" for n in (*names, "images_N")]
        wanted = ", ".join(quoted[:-1]) + " or " + quoted[-1]
        raise FileNotFoundError(f"{root}: no {wanted} folder{where}")
    found = ", ".join(p.name for p in candidates)
    raise SurfSplatInputError(f"{root}: several image folders ({found}); choose one with images=...")


def image_sizes(paths: list[Path]) -> list[tuple[int, int]]:
    """(width, height) of every file, from headers only."""
    return [read_image_size(p) for p in paths]


def load_image_stack(
    paths: list[Path],
    background: tuple[float, float, float] | None,
) -> tuple[Tensor, Tensor | None]:
    """Read same-size images: (rgb [N, 3, H, W], alpha [N, 1, H, W] or None).

    Alpha is returned only when every image has one; a mix of RGB and RGBA files is accepted
    (RGB files count as opaque).
    """
    if not paths:
        raise SurfSplatInputError("no image files to read")
    rgbs: list[Tensor] = []
    alphas: list[Tensor | None] = []
    for p in paths:
        rgb, alpha = read_image(p, background)
        if rgbs and rgb.shape != rgbs[0].shape:
            raise SurfSplatInputError(
                f"{p}: image is {rgb.shape[2]}x{rgb.shape[1]} but {paths[0].name} is "
                f"{rgbs[0].shape[2]}x{rgbs[0].shape[1]}; all views of a scene must share one size"
            )
        rgbs.append(rgb)
        alphas.append(alpha)
    alpha_stack = None
    if any(a is not None for a in alphas):
        alpha_stack = torch.stack([torch.ones_like(rgbs[0][:1]) if a is None else a for a in alphas])
    return torch.stack(rgbs), alpha_stack


def camera_set(
    cameras: Cameras,
    paths: list[Path],
    sizes: list[tuple[int, int]],
    names: list[str],
    near: Tensor | None = None,
    far: Tensor | None = None,
):
    """A reader's `cameras_only` result: a CameraSet from its camera records and the images'
    headers (`sizes`, (width, height) each), without decoding a pixel."""
    from ..cameras import CameraSet

    if len(set(sizes)) != 1:
        (w0, h0), bad = sizes[0], next(i for i, s in enumerate(sizes) if s != sizes[0])
        w, h = sizes[bad]
        raise SurfSplatInputError(
            f"{paths[bad]}: image is {w}x{h} but {paths[0].name} is {w0}x{h0}; all views of a scene must share one size"
        )
    width, height = sizes[0]
    return CameraSet(
        cameras,
        width,
        height,
        names,
        float(near.min()) if near is not None else None,
        float(far.max()) if far is not None else None,
    )
