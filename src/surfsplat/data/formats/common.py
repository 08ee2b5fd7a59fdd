"""Helpers shared by the format readers: validated cameras, same-size image stacks, the photos a
camera file lists that exist, and the lens of each view (undistorted at load to a pinhole)."""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import Tensor

from ...geometry.cameras import Cameras, validate_c2w, validate_intrinsics
from ...geometry.lens import Lens
from ...utils.checks import SurfSplatInputError
from ..images import read_image, read_image_size
from ..posed_images import check_finite_rows, fit_intrinsics

logger = logging.getLogger(__name__)
SHOWN_MISSING = 3  # missing photos named in the warning (the count says how many in all)


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
    lenses: list[Lens] | None = None,
):
    """A reader's `cameras_only` result: a CameraSet from its camera records and the images'
    headers (`sizes`, (width, height) each, after undistortion where `lenses` are given), without
    decoding a pixel."""
    from ..cameras import CameraSet

    if len(set(sizes)) != 1:
        (w0, h0), bad = sizes[0], next(i for i, s in enumerate(sizes) if s != sizes[0])
        w, h = sizes[bad]
        what = "undistorts to" if lenses is not None else "is"
        raise SurfSplatInputError(
            f"{paths[bad]}: image {what} {w}x{h} but {paths[0].name} {what} {w0}x{h0}; "
            "all views of a scene must share one size"
        )
    width, height = sizes[0]
    return CameraSet(
        cameras,
        width,
        height,
        names,
        float(near.min()) if near is not None else None,
        float(far.max()) if far is not None else None,
        lenses,
    )


def present_views(paths: list[Path], source: str) -> list[int]:
    """Indices of the listed photos whose files exist. A capture processed by another tool often lists
    frames whose photo was left out (instant-ngp and nerfstudio train on the ones present): they are
    left out with one warning that counts them and names the first few. Fewer than two remaining is an
    error (the model matches views); a photo that exists but cannot be decoded stays an error where it
    is read."""
    missing = [i for i, p in enumerate(paths) if not p.is_file()]
    if not missing:
        return list(range(len(paths)))
    shown = ", ".join(paths[i].name for i in missing[:SHOWN_MISSING]) + (
        ", ..." if len(missing) > SHOWN_MISSING else ""
    )
    verb = "has" if len(missing) == 1 else "have"
    if len(missing) == len(paths):
        raise SurfSplatInputError(
            f"{source}: every photo listed in it is missing ({len(paths)} frames: {shown}; looked in {paths[0].parent})"
        )
    keep = [i for i in range(len(paths)) if i not in set(missing)]
    if len(keep) < 2:
        raise SurfSplatInputError(
            f"{source}: {len(missing)} of {len(paths)} listed frames {verb} no photo ({shown}); "
            f"only {paths[keep[0]].name} is left and at least two views are needed"
        )
    logger.warning(
        f"{len(missing)} of {len(paths)} frames listed in {source} {verb} no photo ({shown}); they are left out"
    )
    return keep


def lens_view(
    lens: Lens,
    image_size: tuple[int, int],
    source: str,
    allow_downscale: bool,
    camera_source: str | None = None,
    orientation: int = 1,
    c2w: Tensor | None = None,
) -> tuple[Tensor, Lens | None, tuple[int, int], Tensor | None]:
    """What one view is once read: (K [3, 3] float64, the lens at the photo's size or None, (width, height),
    c2w [4, 4] or None).

    A pinhole lens (or a perspective model with zero distortion) is its K, fitted to the photo's size as
    `fit_intrinsics` allows; any other lens is rescaled with the photo and undistorted to the pinhole
    COLMAP's image_undistorter chooses, whose K and size the view then has. Photos in a downscaled folder
    carry the lens rescaled with them (`Lens.rescaled`, COLMAP's Camera::Rescale).

    image_size is the photo as displayed (`read_image_size`) and `orientation` its EXIF orientation: the
    lens describes the STORED pixels (COLMAP's image reader ignores the tag, and so do the tools that write
    transforms.json from COLMAP's cameras), so for orientation 3, 6 or 8 the view's pinhole and its pose
    `c2w` are turned with the photo (`surfsplat.geometry.orientation.displayed_camera`, exact) and its lens
    carries the orientation (`Lens.orientation`: undistorted in the stored frame, then turned). A mirrored
    orientation (2, 4, 5, 7) is one error line. `camera_source` (the camera record) starts the error line of
    a lens with no valid region, and of a mirrored photo."""
    from ...geometry.orientation import displayed_camera, stored_size
    from ..cameras import pinhole_of

    where = camera_source or source
    stored = stored_size(orientation, *image_size)
    K = fit_intrinsics(lens.intrinsics(), (lens.width, lens.height), stored, source, allow_downscale)
    if lens.is_pinhole:
        flat, out_lens, size = pinhole_lens(K, *stored), None, stored
    else:
        out_lens = lens.rescaled(*stored) if stored != (lens.width, lens.height) else lens
        flat = pinhole_of(out_lens, where)
        size = (flat.width, flat.height)
    if orientation == 1:
        return flat.intrinsics(), out_lens, size, c2w
    pose = torch.eye(4, dtype=torch.float64) if c2w is None else c2w
    K_d, c2w_d, size_d = displayed_camera(
        flat.intrinsics(), pose, flat.width, flat.height, orientation, source=f"{where} ({Path(source).name})"
    )
    return K_d, None if out_lens is None else out_lens.turned(orientation), size_d, None if c2w is None else c2w_d


def view_lenses(
    views: list[tuple[Tensor, Lens | None, tuple[int, int], Tensor | None]],
) -> tuple[Tensor, list[Lens] | None, list[tuple[int, int]]]:
    """(K [N, 3, 3], lenses, sizes) of `lens_view` results. `lenses` is None when every view is a
    pinhole, else one Lens a view (a pinhole view's own PINHOLE lens, which needs no undistortion)."""
    Ks = torch.stack([K for K, _, _, _ in views])
    sizes = [size for _, _, size, _ in views]
    if all(lens is None for _, lens, _, _ in views):
        return Ks, None, sizes
    lenses = [
        lens if lens is not None else pinhole_lens(K, *size) for (K, lens, _, _), size in zip(views, sizes, strict=True)
    ]
    return Ks, lenses, sizes


def pinhole_lens(K: Tensor, width: int, height: int) -> Lens:
    """The PINHOLE Lens of K [3, 3] in pixels of width x height."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return Lens("PINHOLE", int(width), int(height), (fx, fy, cx, cy))


def undistort_photo(image: Tensor, lens: Lens, mode: str = "bilinear") -> Tensor:
    """One photo [C, H, W] as read (displayed) undistorted to the lens's pinhole (unchanged for a pinhole)."""
    if lens.is_pinhole:
        return image
    from ..cameras import pinhole_of
    from ..undistort import undistort

    return undistort(image, lens, pinhole_of(lens), mode=mode)


def undistort_views(
    rgb: Tensor, alpha: Tensor | None, lenses: list[Lens] | None, paths: list[Path]
) -> tuple[Tensor, Tensor | None]:
    """The photos [N, 3, H, W] (and alpha masks [N, 1, H, W]) undistorted to their pinholes; as given
    when `lenses` is None. Every view must come out at one size (a scene has one)."""
    if lenses is None:
        return rgb, alpha
    out = [undistort_photo(image, lens) for image, lens in zip(rgb, lenses, strict=True)]
    sizes = {tuple(o.shape[-2:]) for o in out}
    if len(sizes) != 1:
        listing = sorted(f"{w}x{h}" for h, w in sizes)
        raise SurfSplatInputError(
            f"{paths[0].parent}: the photos' lenses undistort to different sizes {listing}; a scene has one size"
        )
    masks = None
    if alpha is not None:
        masks = torch.stack([undistort_photo(a, lens) for a, lens in zip(alpha, lenses, strict=True)])
    return torch.stack(out), masks
