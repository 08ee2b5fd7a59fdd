"""The camera of a photo as displayed, from the camera of its stored pixels and its EXIF orientation.

A photo's EXIF Orientation tag (CIPA DC-008, tag 0x0112) says how its stored pixels are turned or
flipped for display; `surfsplat.data.images.read_image` applies it (Pillow's `exif_transpose`).
Each of the eight values is a flip/transpose of the pixel grid, so in continuous image
coordinates (pixel centres at +0.5, section 2 of the conventions) a stored point (x, y) of a
W x H image lands at (x', y') = M (x, y) + b in the displayed image, M a 2x2 signed permutation:

    1 (0, 0) identity          2 (W - x, y) mirror left-right     3 (W - x, H - y) turn 180
    4 (x, H - y) mirror top-bottom   5 (y, x) transpose            6 (H - y, x) turn 90 clockwise
    7 (H - y, W - x) transverse      8 (y, W - x) turn 90 counter-clockwise

(Pillow's FLIP_LEFT_RIGHT, ROTATE_180, FLIP_TOP_BOTTOM, TRANSPOSE, ROTATE_270, TRANSVERSE and
ROTATE_90; 5-8 swap width and height.) The camera follows: with A = [[M, b], [0, 1]] and the camera
axes changed by R_a = [[M, 0], [0, 1]] (x_cam' = R_a x_cam), the displayed pixel of a camera point is
A K x_cam / z = K' x_cam' / z with K' = A K R_a^T and c2w' = c2w [[R_a^T, 0], [0, 1]]. For the turns
(1, 3, 6, 8) det M = +1: R_a rotates the camera about its optical axis, K' is again a pinhole
(fx and fy swap for 6 and 8, the principal point moves with the pixels) and the map is exact.

Mirrored orientations (2, 4, 5, 7) have det M = -1: the displayed photo is a mirror image, and the
only camera that "sees" it has a reflected frame (det R = -1), which is not a rigid camera and which
no stage of this package accepts. `displayed_camera` refuses them by default with one clear line;
`reflection=True` returns the reflected c2w, exact for projecting points (an overlay) only.

Which image a camera file describes: COLMAP, nerfstudio and instant-ngp calibrate the stored pixels
(their image readers ignore the tag), while cameras written by this package (`surfsplat poses`) are
of the displayed photos. `camera_is_of_stored_image` decides by size where size can tell: for
orientations 5-8 a camera calibrated at the stored size (w, h) of a photo displayed as (h, w) is the
stored image's. For 2-4 (and square photos) both images have one size and the file's format decides.

A camera with a lens (`surfsplat.geometry.lens.Lens.orientation`) is not mapped through the turn:
COLMAP's choice of the undistorted pinhole (`undistorted_pinhole`, its `UndistortCamera`) is not
symmetric under a turn of the image (its border formula uses cx on one side and W - 0.5 - cx on
the other), so a turned lens would undistort to another pinhole than the turned one. The photo is
taken back to its stored pixels instead (`stored_image`, an exact permutation of pixels), undistorted
there as COLMAP's image_undistorter would, and the pinhole photo turned for display (`displayed_image`)
with its pinhole camera (`displayed_camera`): every step exact.

The arithmetic is a 3x3 product written here: no library maps a pinhole camera through an EXIF
orientation (pycolmap's and OpenCV's cameras have no notion of it). The pixel permutations of
`displayed_image` are torch's flip and transpose; they are what Pillow's `exif_transpose` does to a
decoded photo (tested against it), written for tensors so that an undistorted photo, a mask or a depth
map on any device turns the same way.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError

# EXIF orientation -> (M row-major (m00, m01, m10, m11), b as multiples of (W, H) of the stored image)
_TRANSFORMS: dict[int, tuple[tuple[int, int, int, int], tuple[tuple[int, int], tuple[int, int]]]] = {
    1: ((1, 0, 0, 1), ((0, 0), (0, 0))),
    2: ((-1, 0, 0, 1), ((1, 0), (0, 0))),  # x' = W - x
    3: ((-1, 0, 0, -1), ((1, 0), (0, 1))),  # x' = W - x, y' = H - y
    4: ((1, 0, 0, -1), ((0, 0), (0, 1))),  # y' = H - y
    5: ((0, 1, 1, 0), ((0, 0), (0, 0))),  # x' = y, y' = x
    6: ((0, -1, 1, 0), ((0, 1), (0, 0))),  # x' = H - y, y' = x
    7: ((0, -1, -1, 0), ((0, 1), (1, 0))),  # x' = H - y, y' = W - x
    8: ((0, 1, -1, 0), ((0, 0), (1, 0))),  # x' = y, y' = W - x
}
MIRRORED = (2, 4, 5, 7)
TRANSPOSED = (5, 6, 7, 8)  # width and height swap
INVERSE = {1: 1, 2: 2, 3: 3, 4: 4, 5: 5, 6: 8, 7: 7, 8: 6}  # the orientation that undoes each one


def _check(orientation: int) -> int:
    if isinstance(orientation, bool) or orientation not in _TRANSFORMS:
        raise SurfSplatInputError(f"orientation: expected an EXIF orientation 1-8, got {orientation!r}")
    return int(orientation)


def displayed_size(orientation: int, width: int, height: int) -> tuple[int, int]:
    """(width, height) of the displayed photo of a stored width x height image."""
    return (height, width) if _check(orientation) in TRANSPOSED else (width, height)


def stored_size(orientation: int, width: int, height: int) -> tuple[int, int]:
    """(width, height) of the stored pixels of a photo displayed at width x height."""
    return displayed_size(orientation, width, height)  # every transform is its size's own inverse


def displayed_image(image: Tensor, orientation: int) -> Tensor:
    """The pixels [..., H, W] of a stored image as the orientation displays them ([..., W, H] for 5-8).

    From the table of the module doc: a stored pixel (row i, column j) lands at the displayed pixel whose
    centre is M (j + 0.5, i + 0.5) + b, e.g. for 6 at row j, column H - 1 - i (transpose, then flip left-right)."""
    orientation = _check(orientation)
    rows, cols = -2, -1
    if orientation in TRANSPOSED:
        image = image.transpose(rows, cols)
    flips = {1: (), 2: (cols,), 3: (rows, cols), 4: (rows,), 5: (), 6: (cols,), 7: (rows, cols), 8: (rows,)}
    return image.flip(flips[orientation]) if flips[orientation] else image


def stored_image(image: Tensor, orientation: int) -> Tensor:
    """The stored pixels [..., H, W] of an image displayed with this orientation (`displayed_image` undone)."""
    return displayed_image(image, INVERSE[_check(orientation)])


def orientation_transform(orientation: int, width: int, height: int, dtype=torch.float64) -> Tensor:
    """A [3, 3]: homogeneous stored image coordinates (x, y, 1) of a width x height image -> displayed ones."""
    (m00, m01, m10, m11), ((bxw, bxh), (byw, byh)) = _TRANSFORMS[_check(orientation)]
    return torch.tensor(
        [[m00, m01, bxw * width + bxh * height], [m10, m11, byw * width + byh * height], [0, 0, 1]], dtype=dtype
    )


def camera_axes_change(orientation: int, dtype=torch.float64) -> Tensor:
    """R_a [3, 3]: camera-frame coordinates of the stored image's camera -> the displayed one's."""
    (m00, m01, m10, m11), _ = _TRANSFORMS[_check(orientation)]
    return torch.tensor([[m00, m01, 0], [m10, m11, 0], [0, 0, 1]], dtype=dtype)


def displayed_camera(
    K: Tensor,  # [..., 3, 3] in pixels of the stored width x height image
    c2w: Tensor,  # [..., 4, 4] OpenCV camera-to-world of the stored image
    width: int,
    height: int,
    orientation: int,
    *,
    reflection: bool = False,
    source: str = "camera",
) -> tuple[Tensor, Tensor, tuple[int, int]]:
    """(K', c2w', (width', height')): the pinhole camera of the photo as `read_image` shows it.

    Call it where a camera given for the STORED pixels meets a photo read as displayed: in a
    camera-file reader (COLMAP, nerfstudio / instant-ngp transforms.json) once per view with that
    view's `surfsplat.data.images.image_orientation`, after undistortion to a pinhole (the lens
    model is of the stored pixels too) and before any resize or crop. Cameras made from displayed
    photos (estimated here, or a JSON file `surfsplat poses` wrote) must not pass through it.

    Turns (orientations 1, 3, 6, 8) are exact and rigid. Mirrored ones (2, 4, 5, 7) raise
    SurfSplatInputError unless `reflection=True`, which returns the reflected c2w (det R = -1): it
    projects points exactly, but it is not a rigid camera (see the module docstring).
    A skewed K (K[0, 1] != 0) through a transposing orientation has no upper-triangular K' and is refused.
    """
    orientation = _check(orientation)
    if orientation in MIRRORED and not reflection:
        raise SurfSplatInputError(
            f"{source}: EXIF orientation {orientation} shows the photo mirrored; a mirror image is not a view a "
            "camera takes (its camera would be a reflection); save the photo unmirrored to use it with a camera"
        )
    A = orientation_transform(orientation, width, height, K.dtype).to(K.device)
    R_a = camera_axes_change(orientation, K.dtype).to(K.device)
    K_new = A @ K @ R_a.T
    if orientation in TRANSPOSED and bool((K[..., 0, 1] != 0).any()):
        raise SurfSplatInputError(
            f"{source}: a skewed K (K[0, 1] = {float(K.reshape(-1, 3, 3)[0, 0, 1]):g}) has no pinhole camera after "
            f"the transpose of EXIF orientation {orientation}"
        )
    turn = torch.eye(4, dtype=c2w.dtype, device=c2w.device)
    turn[:3, :3] = R_a.T.to(c2w.dtype)
    return K_new, c2w @ turn, displayed_size(orientation, width, height)


def camera_is_of_stored_image(
    calibrated: tuple[int, int], displayed: tuple[int, int], orientation: int, tol: float = 0.01
) -> bool | None:
    """Whether a camera calibrated at `calibrated` (width, height) describes the stored pixels of a photo
    displayed at `displayed` with this orientation, as far as the sizes tell: True when its aspect
    ratio is the stored image's and not the displayed one's (orientations 5-8 of a non-square photo),
    False when it is the displayed one's only, None when both have one aspect (orientations 1-4,
    square photos) or neither does (the caller reports the mismatch)."""
    w, h = calibrated
    stored = stored_size(_check(orientation), *displayed)
    aspect = w / h

    def fits(size: tuple[int, int]) -> bool:
        return abs(aspect - size[0] / size[1]) <= tol * aspect

    of_stored, of_displayed = fits(stored), fits(displayed)
    return None if of_stored == of_displayed else of_stored
