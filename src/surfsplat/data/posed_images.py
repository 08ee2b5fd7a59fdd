"""`PosedImages`: posed images of one capture in the package's conventions, whatever the source format."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError, check_tensor


@dataclass
class PosedImages:
    """N posed images.

    images:  [N, 3, H, W] float32 in [0, 1]
    cameras: N cameras, OpenCV camera-to-world, K in pixels of these images
    names:   N image names (file names, or frame timestamps)
    near, far: [N] depth bounds where the source provides them (LLFF bounds, DTU sphere), else None
    masks:   [N, 1, H, W] in [0, 1] (foreground masks, alpha) where the source provides them, else None
    depths:  [N, 1, H, W] camera-z depth where the source provides it, else None (0 = no measurement)
    source:  where the scene was read from (for messages)
    """

    images: Tensor  # [N, 3, H, W]
    cameras: Cameras
    names: list[str]
    near: Tensor | None = None  # [N]
    far: Tensor | None = None  # [N]
    masks: Tensor | None = None  # [N, 1, H, W]
    depths: Tensor | None = None  # [N, 1, H, W]
    source: str = ""
    # format-specific metadata (e.g. DTU scale matrix; "lenses": each view's source Lens where its photo was
    # undistorted at load)
    extras: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = self.source or "scene"
        images = check_tensor(f"{where}: images", self.images, ("N", 3, None, None))
        n, _, h, w = images.shape
        if n == 0:
            raise SurfSplatInputError(f"{where}: no images")
        if len(self.cameras) != n:
            raise SurfSplatInputError(f"{where}: {n} images but {len(self.cameras)} cameras")
        if len(self.names) != n:
            raise SurfSplatInputError(f"{where}: {n} images but {len(self.names)} names")
        for name in ("near", "far"):
            value = getattr(self, name)
            if value is not None:
                check_tensor(f"{where}: {name}", value, (n,))
                if bool((value <= 0).any()):
                    raise SurfSplatInputError(f"{where}: {name} must be positive, got min {float(value.min()):.4g}")
        if self.near is not None and self.far is not None and bool((self.far <= self.near).any()):
            raise SurfSplatInputError(f"{where}: far must exceed near for every view")
        for name in ("masks", "depths"):
            value = getattr(self, name)
            if value is not None:
                check_tensor(f"{where}: {name}", value, (n, 1, h, w))

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.images.shape[2]

    @property
    def width(self) -> int:
        return self.images.shape[3]

    def select(self, indices: list[int] | Tensor) -> PosedImages:
        """The sub-scene of the given views, in the given order."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        if idx.numel() and (int(idx.min()) < -len(self) or int(idx.max()) >= len(self)):
            raise SurfSplatInputError(
                f"{self.source or 'scene'}: view index out of range for {len(self)} views: {idx.tolist()}"
            )

        def pick(t: Tensor | None) -> Tensor | None:
            return None if t is None else t[idx]

        extras = dict(self.extras)
        if "lenses" in extras:  # one per view, like the tensors
            extras["lenses"] = [extras["lenses"][i] for i in idx.tolist()]

        return PosedImages(
            images=self.images[idx],
            cameras=self.cameras[idx],
            names=[self.names[i] for i in idx.tolist()],
            near=pick(self.near),
            far=pick(self.far),
            masks=pick(self.masks),
            depths=pick(self.depths),
            source=self.source,
            extras=extras,
        )


def fit_intrinsics(
    K: Tensor,
    calibrated_size: tuple[int, int],
    image_size: tuple[int, int],
    source: str,
    allow_downscale: bool,
) -> Tensor:
    """Intrinsics [..., 3, 3] calibrated at `calibrated_size` (W, H) adapted to an image of `image_size`.

    Equal sizes: K unchanged. A folder of downscaled images (LLFF/COLMAP `images_N`, DTU
    `images_4`): K' = diag(W'/W, H'/H, 1) K, exact under the pixel-centre-at-(j+0.5) convention,
    accepted only when `allow_downscale` and both axes shrink by the same factor up to the
    rounding of half a pixel. Anything else is an error naming the file and both sizes.
    """
    (cw, ch), (iw, ih) = calibrated_size, image_size
    if (cw, ch) == (iw, ih):
        return K
    factor = cw / iw
    # The height must follow the width's factor up to the rounding of the resize (half a pixel).
    uniform = abs(ch / factor - ih) <= 0.5
    if not (allow_downscale and uniform and factor > 1):
        raise SurfSplatInputError(
            f"{source}: image is {iw}x{ih} but the intrinsics are for {cw}x{ch} "
            f"(expected the calibrated size{' or a uniform downscale of it' if allow_downscale else ''})"
        )
    S = torch.tensor([iw / cw, ih / ch, 1.0], dtype=K.dtype)
    return K * S[:, None]


def check_finite_rows(array: Tensor, source: str, what: str) -> None:
    """Raise naming the first row of `array` [N, ...] that holds NaN or inf."""
    flat = array.reshape(array.shape[0], -1)
    bad = ~torch.isfinite(flat).all(dim=1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise SurfSplatInputError(f"{source}: {what} {i} contains NaN or inf: {flat[i].tolist()}")


def downscale_from_folder(folder: Path) -> bool:
    """Whether an image folder is a downscaled copy by naming convention (`images_4`, `images_8`, ...)."""
    name = folder.name
    return name.startswith("images_") and name[len("images_") :].isdigit()
