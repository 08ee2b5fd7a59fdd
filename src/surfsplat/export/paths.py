"""Camera paths for videos and meshes: smooth interpolation between posed views and a turntable.

    path = interpolate_cameras(context, num_frames=60)          # through the views, in order
    orbit = turntable(context, focus=point, num_frames=48)      # swing around a point of the scene
    cams = load_cameras("cameras.json")                          # or a COLMAP model / scene folder

Rotations are interpolated on the unit quaternion sphere (slerp), so every in-between camera is an
exact rotation; centres and intrinsics are interpolated linearly. All paths keep the package's
camera convention (OpenCV camera-to-world, K in pixels of the source views' image size).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.rotations import matrix_to_quat, quat_to_matrix, skew
from ..utils.checks import SurfSplatInputError, check_tensor


def slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Spherical interpolation of unit quaternions q0, q1 [4] at fractions t [T] -> [T, 4].

    q1 is flipped to q0's hemisphere first (q and -q are the same rotation), so the path takes the
    short way; nearly equal rotations fall back to normalized linear interpolation, whose error
    there is below float precision.
    """
    q0 = q0 / q0.norm()
    q1 = q1 / q1.norm()
    dot = torch.dot(q0, q1)
    if dot < 0:
        q1, dot = -q1, -dot
    t = t[:, None].to(q0)
    if dot > 1 - 1e-9:
        out = q0 + t * (q1 - q0)
        return out / out.norm(dim=-1, keepdim=True)
    theta = torch.arccos(dot.clamp(-1.0, 1.0))
    return (torch.sin((1 - t) * theta) * q0 + torch.sin(t * theta) * q1) / torch.sin(theta)


def interpolate_cameras(cameras: Cameras, num_frames: int) -> Cameras:
    """`num_frames` cameras along the views of `cameras` in their order, first and last included.

    The path parameter is spread over the segments in proportion to the distance between camera
    centres (equal steps for co-located cameras), so the video moves at a constant speed.
    """
    _check_count("num_frames", num_frames, 2)
    n = len(cameras)
    if n < 2:
        raise SurfSplatInputError(f"cameras: expected at least 2 cameras to interpolate between, got {n}")
    c2w = cameras.c2w.to(torch.float64)
    K = cameras.K.to(torch.float64)
    f64 = {"dtype": torch.float64, "device": c2w.device}  # the path is made where the cameras are
    quats = matrix_to_quat(c2w[:, :3, :3])
    centres = c2w[:, :3, 3]
    lengths = (centres[1:] - centres[:-1]).norm(dim=-1)
    if float(lengths.sum()) <= 1e-12:
        lengths = torch.ones(n - 1, **f64)
    knots = torch.cat([torch.zeros(1, **f64), torch.cumsum(lengths, 0) / lengths.sum()])
    s = torch.linspace(0, 1, num_frames, **f64)
    segment = torch.searchsorted(knots[1:-1], s, right=True)  # which pair of views each frame falls between
    out_c2w = torch.eye(4, **f64).repeat(num_frames, 1, 1)
    out_K = torch.empty(num_frames, 3, 3, **f64)
    for k in range(n - 1):
        sel = segment == k
        if not bool(sel.any()):
            continue
        span = (knots[k + 1] - knots[k]).clamp_min(1e-12)
        t = ((s[sel] - knots[k]) / span).clamp(0, 1)
        out_c2w[sel, :3, :3] = quat_to_matrix(slerp(quats[k], quats[k + 1], t))
        out_c2w[sel, :3, 3] = centres[k] + t[:, None] * (centres[k + 1] - centres[k])
        out_K[sel] = K[k] + t[:, None, None] * (K[k + 1] - K[k])
    return Cameras(out_c2w.to(cameras.c2w.dtype), out_K.to(cameras.K.dtype))


def mean_camera(cameras: Cameras) -> tuple[Tensor, Tensor]:
    """(c2w [4, 4], K [3, 3]): the average centre, the normalized quaternion mean and the mean K."""
    c2w = cameras.c2w.to(torch.float64)
    quats = matrix_to_quat(c2w[:, :3, :3])
    signs = torch.where((quats @ quats[0]) < 0, -1.0, 1.0).to(quats)  # one hemisphere before averaging
    q = (quats * signs[:, None]).mean(0)
    out = torch.eye(4, dtype=torch.float64, device=c2w.device)
    out[:3, :3] = quat_to_matrix(q)
    out[:3, 3] = c2w[:, :3, 3].mean(0)
    return out, cameras.K.to(torch.float64).mean(0)


def axis_angle_matrix(axis: Tensor, angle: float) -> Tensor:
    """Rotation [3, 3] by `angle` radians about the unit `axis` [3] (Rodrigues' formula)."""
    a = axis / axis.norm()
    A = skew(a)
    return torch.eye(3, dtype=a.dtype, device=a.device) + math.sin(angle) * A + (1 - math.cos(angle)) * (A @ A)


def turntable(
    cameras: Cameras,
    focus: Tensor,  # [3] world point the path turns around (e.g. the scene's median surface point)
    num_frames: int,
    degrees: float = 30.0,
    loops: int = 1,
) -> Cameras:
    """A turntable video path: the mean camera swings around `focus` about its own vertical axis.

    Frame f sits at angle (degrees / 2) * sin(2 pi loops f / num_frames): a smooth back-and-forth
    sweep of `degrees` in total that starts and ends at the mean view, so it stays on the side of
    the scene the context views saw (a feed-forward reconstruction has no back side to show).
    """
    _check_count("num_frames", num_frames, 2)
    check_tensor("focus", focus, (3,))
    if not 0 < degrees <= 360:
        raise SurfSplatInputError(f"degrees: expected a sweep in (0, 360], got {degrees}")
    c2w, K = mean_camera(cameras)
    p = focus.to(torch.float64)
    up = -c2w[:3, 1]  # OpenCV y points down in the image
    out_c2w = torch.eye(4, dtype=torch.float64, device=c2w.device).repeat(num_frames, 1, 1)
    for f in range(num_frames):
        angle = math.radians(degrees / 2) * math.sin(2 * math.pi * loops * f / num_frames)
        R = axis_angle_matrix(up, angle)
        out_c2w[f, :3, :3] = R @ c2w[:3, :3]
        out_c2w[f, :3, 3] = p + R @ (c2w[:3, 3] - p)
    return Cameras(out_c2w.to(cameras.c2w.dtype), K.expand(num_frames, 3, 3).to(cameras.K.dtype).clone())


def focus_point(depths: Tensor, valid: Tensor, cameras: Cameras) -> Tensor:
    """[3] a point to turn around: the mean camera's centre plus its viewing axis times the median
    rendered depth of the valid pixels (depths [V, 1, H, W] rendered from `cameras`; valid: bool of
    the same shape, e.g. alpha >= the forced-alpha-blending threshold)."""
    check_tensor("depths", depths, ("V", 1, "H", "W"))
    if tuple(valid.shape) != tuple(depths.shape) or valid.dtype != torch.bool:
        raise SurfSplatInputError(
            f"valid: expected a bool tensor of shape {tuple(depths.shape)}, got {valid.dtype} {tuple(valid.shape)}"
        )
    valid = valid & (depths > 0)
    if not bool(valid.any()):
        raise SurfSplatInputError("depths: no rendered pixel is valid (covered); nothing to turn around")
    distance = depths[valid].to(torch.float64).median()
    c2w, _ = mean_camera(cameras)
    return c2w[:3, 3] + distance * c2w[:3, 2]


def _check_count(name: str, value: int, minimum: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise SurfSplatInputError(f"{name}: expected an integer >= {minimum}, got {value!r}")
