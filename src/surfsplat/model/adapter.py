"""Gaussian adapter: per-pixel depth and raw head channels -> world-frame surfels.

This is where the paper's two contributions live (Sec. 3.3 and 3.4):

- the surface continuity prior, `surface_frames` below (Eqs. 2-5 and 8): a surfel's rotation and
  base scales are not regressed but derived from its neighbours' 3D positions;
- forced alpha blending: opacities are bounded by tau_opa (here `opacity_max`), and the renderer
  divides colour by alpha wherever alpha >= tau_alpha (Eq. 11); `GaussianAdapter.alpha_threshold`
  tells the renderer which tau_alpha applies.

Modes (`AdapterConfig.mode`):

- "paper" (default): the method as the paper describes it, with the geometry done in each camera's
  own frame, exact Rodrigues rotations, and SH rotated to the world frame correctly.
- "official": the released code's computation, quirks included, so that released checkpoints give
  their published numbers (world-frame Sobel, a rotation formula that is not Rodrigues', the camera
  rotation applied twice, world X/Z and Y/Z scale components, (x, y, z, w) quaternions, e3nn-ordered
  SH rotation). Its covariances travel as `Gaussians.explicit_covariances`, so EWA renders match.

Ablations of the paper's Table 4 are configuration: `prior="none"` regresses rotation and scales per
pixel (DepthSplat's 3DGS adapter), `opacity_max=1.0` is "w/o FAB", `primitive="gaussian3d"` makes
3D Gaussians (a 3DGS baseline, rendered with mode="ewa").

Head channel layout (the release's): 0 opacity logit, 1-2 sub-pixel offsets (x, y), then the scale
block (2 multipliers; 3 with primitive="gaussian3d"), then with prior="none" a raw (w, x, y, z)
quaternion, then SH as (rgb, (d+1)^2), i.e. channel `sh_start + c * (d+1)^2 + k`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor

from ..geometry.cameras import validate_c2w, validate_intrinsics
from ..geometry.gaussians import THIN_SCALE, Gaussians
from ..geometry.rotations import matrix_to_quat, quat_to_matrix, skew
from ..geometry.sh import SH_C0, num_sh_bases
from ..geometry.sh_rotation import SHConvention, sh_rotation_matrix
from ..utils.checks import SurfSplatInputError, check_tensor

# A cross product counts as degenerate (normal undefined) below this sine of the tangent angle.
_DEGENERATE_SINE = 1e-6


@dataclass
class AdapterConfig:
    """Configuration of the Gaussian adapter; defaults are the paper's (and the release's) values."""

    mode: Literal["paper", "official"] = "paper"  # official = reproduces the release, quirks included
    prior: Literal["surface", "none"] = "surface"  # none = rotation/scales regressed per pixel (DepthSplat-style)
    primitive: Literal["surfel", "gaussian3d"] = "surfel"  # gaussian3d = 3D Gaussians (3DGS baseline)
    opacity_max: float = 0.6  # tau_opa of Sec. 3.4; 1.0 = "w/o FAB" (also turns alpha normalization off)
    sh_degree: int = 2  # SH degree of the colour, 0..3
    tangent_clamp: float = 0.1  # tangent components clamped to [-g, g] before the scales (depth edges)
    # Unit of g: "world" (the paper's and the release's absolute bound, so the largest surfel depends
    # on the scene's scale) or "footprint" (g times the pixel's footprint z / f, scale-invariant).
    tangent_clamp_unit: Literal["world", "footprint"] = "world"
    scale_multiplier_range: float = 3.0  # multipliers clamp(softplus(raw), 1/r, r) (Eq. 9)
    # Gradient of that clamp: "clamp" (zero outside [1/r, r], plain autograd) or "inward" (the same
    # values, but a multiplier stuck at a bound still gets the gradients that pull it back inside).
    multiplier_gradient: Literal["clamp", "inward"] = "clamp"
    # Smallest tangent scale in pixel footprints z / f (None: no floor, the paper's). Eq. 9's 1/r
    # bound alone lets a surfel shrink to a third of its base scale, so a model can trade a closed
    # surface for sharper x1 texture; a floor of 0.5 keeps every surfel at least half a pixel wide at
    # its depth, whatever the scene's scale. It uses multiplier_gradient's rule at the floor.
    scale_floor: float | None = None
    alpha_threshold_train: float = 0.1  # tau_alpha of Eq. 11 while training
    alpha_threshold_eval: float = 0.001  # tau_alpha of Eq. 11 at evaluation
    scale_min: float = 1e-10  # final scales clamped to [scale_min, scale_max] (the release's bounds)
    scale_max: float = 3.0
    init_sh_from_image: bool = True  # add the input colour to the SH DC term (Sec. 3.4)
    regressed_scale_shift: float = 4.0  # prior="none": scale = softplus(raw - shift), DepthSplat's form

    def __post_init__(self) -> None:
        choices = {
            "mode": ("paper", "official"),
            "prior": ("surface", "none"),
            "primitive": ("surfel", "gaussian3d"),
            "tangent_clamp_unit": ("world", "footprint"),
            "multiplier_gradient": ("clamp", "inward"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise SurfSplatInputError(f"adapter.{name}: expected one of {allowed}, got {getattr(self, name)!r}")
        if self.mode == "official" and (self.prior, self.primitive) != ("surface", "surfel"):
            raise SurfSplatInputError(
                "adapter.mode: 'official' reproduces the release, which has prior='surface' and primitive='surfel'; "
                f"got prior={self.prior!r}, primitive={self.primitive!r}"
            )
        release_rules = (self.tangent_clamp_unit, self.multiplier_gradient, self.scale_floor)
        if self.mode == "official" and release_rules != ("world", "clamp", None):
            raise SurfSplatInputError(
                "adapter.mode: 'official' reproduces the release, which clamps tangents in world units with a plain "
                f"clamp and no scale floor; got tangent_clamp_unit={self.tangent_clamp_unit!r}, "
                f"multiplier_gradient={self.multiplier_gradient!r}, scale_floor={self.scale_floor!r}"
            )
        floor = self.scale_floor
        if floor is not None and (isinstance(floor, bool) or not isinstance(floor, (int, float)) or not 0 < floor < 4):
            raise SurfSplatInputError(
                f"adapter.scale_floor: expected None or a value in (0, 4) footprints, got {floor!r}"
            )
        if not 0 < self.opacity_max <= 1:
            raise SurfSplatInputError(f"adapter.opacity_max: expected a value in (0, 1], got {self.opacity_max}")
        if not 0 <= self.sh_degree <= 3:
            raise SurfSplatInputError(f"adapter.sh_degree: expected 0..3, got {self.sh_degree}")
        if not self.tangent_clamp > 0:
            raise SurfSplatInputError(f"adapter.tangent_clamp: expected a positive bound, got {self.tangent_clamp}")
        if not self.scale_multiplier_range >= 1:
            raise SurfSplatInputError(
                f"adapter.scale_multiplier_range: expected a value >= 1, got {self.scale_multiplier_range}"
            )
        if not 0 < self.scale_min < self.scale_max:
            raise SurfSplatInputError(
                f"adapter.scale_min/scale_max: expected 0 < min < max, got {self.scale_min}, {self.scale_max}"
            )


@dataclass
class AdapterOutput:
    """What the adapter returns; N = V * H * W Gaussians in (view, row, column) order."""

    gaussians: Gaussians  # batched: means [B, N, 3], ...; official mode fills explicit_covariances
    scales_mul: Tensor  # [B, N, 2] scale multipliers (ones with prior="none")
    normals: Tensor  # [B, N, 3] unit world normals (official: before the sign flip, as the release)
    scales: Tensor  # [B, N, 3] final scales incl. the third (1e-10 for surfels)
    rotations: Tensor  # [B, N, 4] world quaternions (w, x, y, z); official: the release's (x, y, z, w), unnormalized


@dataclass
class SurfaceFrames:
    """Per-pixel surface geometry from a camera-frame point map (the surface continuity prior)."""

    normals: Tensor  # [..., H, W, 3] unit normals with n_z >= 0; (0, 0, 1) where undefined
    rotations: Tensor  # [..., H, W, 3, 3] rotations with R e_z = n (Rodrigues, Eq. 4)
    base_scales: Tensor  # [..., H, W, 2] (sqrt(t1x^2 + t1z^2), sqrt(t2y^2 + t2z^2)) (Eq. 8)
    tangents: Tensor  # [..., H, W, 2, 3] Sobel tangents t1 (rightward), t2 (downward), unclamped (Eq. 2)


# ---------------------------------------------------------------------------------------------- geometry
def pixel_centers(
    height: int, width: int, device: torch.device | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """[H, W, 2] pixel centres (x, y) = (column + 0.5, row + 0.5) in pixels (the package convention)."""
    ys = torch.arange(height, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack((grid_x, grid_y), dim=-1)


def unproject_depth(depths: Tensor, K: Tensor, offsets: Tensor | None = None) -> Tensor:
    """Camera-frame points P = depth * K^-1 [x, y, 1] at pixel centres (plus sub-pixel offsets).

    depths:  [..., H, W] camera z
    K:       [..., 3, 3] intrinsics in pixels of the H x W map
    offsets: [..., H, W, 2] optional shifts (x, y) in pixels added to the pixel centres
    returns  [..., H, W, 3]
    """
    H, W = depths.shape[-2:]
    xy = pixel_centers(H, W, depths.device, depths.dtype)
    if offsets is not None:
        xy = xy + offsets
    homogeneous = torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)  # [..., H, W, 3]
    K_inv = torch.linalg.inv_ex(K).inverse[..., None, None, :, :]  # inv_ex: no error read on the host
    rays = (K_inv @ homogeneous[..., None]).squeeze(-1)  # z = 1 for a pinhole K
    return rays * depths[..., None]


def sobel_tangents(points: Tensor) -> tuple[Tensor, Tensor]:
    """Rightward and downward 3x3 Sobel derivatives (kernels / 8) of a point map.

    t1 = ([-1 0 1; -2 0 2; -1 0 1] / 8) * P and t2 = its transpose * P, i.e. central differences
    averaged over the three neighbouring rows (columns) with weights 1, 2, 1. The filters run on
    the valid interior; the one-pixel border takes its nearest interior value (replicate padding of
    the result, as the release does), so a plane gets its exact per-pixel step everywhere.
    points: [..., H, W, 3] with H, W >= 3 -> (t1, t2), each [..., H, W, 3]
    """
    H, W = points.shape[-3:-1]
    if H < 3 or W < 3:
        raise SurfSplatInputError(f"points: the 3x3 Sobel filter needs maps of at least 3 x 3 pixels, got {H} x {W}")
    p = points
    dx = p[..., :, 2:, :] - p[..., :, :-2, :]  # [..., H, W-2, 3] central differences along a row
    dy = p[..., 2:, :, :] - p[..., :-2, :, :]  # [..., H-2, W, 3] along a column
    t1 = (dx[..., :-2, :, :] + 2 * dx[..., 1:-1, :, :] + dx[..., 2:, :, :]) / 8  # [..., H-2, W-2, 3]
    t2 = (dy[..., :, :-2, :] + 2 * dy[..., :, 1:-1, :] + dy[..., :, 2:, :]) / 8
    rows = (torch.arange(H, device=p.device) - 1).clamp(0, H - 3)
    cols = (torch.arange(W, device=p.device) - 1).clamp(0, W - 3)

    def replicate(t: Tensor) -> Tensor:
        return t.index_select(-3, rows).index_select(-2, cols)

    return replicate(t1), replicate(t2)


def _safe_sqrt(x: Tensor) -> Tensor:
    """sqrt with a finite gradient at 0 (the value there is 1e-15, below any scale clamp)."""
    return x.clamp_min(1e-30).sqrt()


def rodrigues_from_z(normals: Tensor) -> Tensor:
    """The rotation taking n0 = (0, 0, 1) to each unit normal n with n_z >= 0 (paper Eq. 4).

    v = n0 x n, c = n0 . n, R = I + [v]x + [v]x^2 / (1 + c); this is the paper's
    (1 - c) / |v|^2 factor rewritten with |v|^2 = 1 - c^2, which stays finite at v = 0.
    normals: [..., 3] -> [..., 3, 3]
    """
    nx, ny, nz = normals.unbind(-1)
    v = torch.stack((-ny, nx, torch.zeros_like(nx)), dim=-1)
    V = skew(v)
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    return eye + V + (V @ V) / (1 + nz)[..., None, None]


def surface_frames(points: Tensor, tangent_clamp: float | tuple[Tensor, Tensor] | None = None) -> SurfaceFrames:
    """The surface continuity prior (paper Sec. 3.3): normals, rotations and base scales per pixel.

    points: [..., H, W, 3] point map in a camera frame with OpenCV axes (x right, y down, z forward),
            e.g. `unproject_depth(depth, K)`; H, W >= 3.
    tangent_clamp: clamp each tangent component to [-g, g] before the scales (not the normals), so
            depth discontinuities do not make huge surfels; a float g for every pixel, or per-pixel
            bounds (g_u, g_v), each [..., H, W, 1], for t1 and t2 (see `footprint_bounds`); None
            leaves them unclamped.

    Eq. 2: t1, t2 = rightward and downward Sobel tangents (virtual neighbours minus the centre).
    Eq. 3: n = (t1 x t2) / |t1 x t2|, oriented so n_z >= 0: n0 = (0, 0, 1) is a fronto-parallel
           surfel facing away from the camera. Where the cross product vanishes (constant or zero
           depth, collinear tangents) the normal is undefined and n0 is used.
    Eq. 4-5: R = Rodrigues rotation taking n0 to n; R_surf = R R0 = R.
    Eq. 8: base scales sqrt(t1x^2 + t1z^2), sqrt(t2y^2 + t2z^2) (camera-frame components).
    """
    if points.ndim < 3 or points.shape[-1] != 3:
        raise SurfSplatInputError(f"points: expected shape [..., H, W, 3], got {tuple(points.shape)}")
    t1, t2 = sobel_tangents(points)

    cross = torch.linalg.cross(t1, t2, dim=-1)
    cross_sq = cross.square().sum(-1, keepdim=True)
    scale_sq = t1.square().sum(-1, keepdim=True) * t2.square().sum(-1, keepdim=True)
    defined = cross_sq > (_DEGENERATE_SINE**2) * scale_sq
    n = cross / _safe_sqrt(cross_sq)
    n = torch.where(n[..., 2:] < 0, -n, n)
    n0 = torch.zeros_like(n)
    n0[..., 2] = 1
    normals = torch.where(defined, n, n0)
    rotations = rodrigues_from_z(normals)

    if isinstance(tangent_clamp, tuple):
        g_u, g_v = tangent_clamp
        t1c, t2c = torch.maximum(torch.minimum(t1, g_u), -g_u), torch.maximum(torch.minimum(t2, g_v), -g_v)
    elif tangent_clamp is not None:
        t1c, t2c = t1.clamp(-tangent_clamp, tangent_clamp), t2.clamp(-tangent_clamp, tangent_clamp)
    else:
        t1c, t2c = t1, t2
    base_scales = torch.stack(
        (
            _safe_sqrt(t1c[..., 0].square() + t1c[..., 2].square()),
            _safe_sqrt(t2c[..., 1].square() + t2c[..., 2].square()),
        ),
        dim=-1,
    )
    return SurfaceFrames(normals, rotations, base_scales, torch.stack((t1, t2), dim=-2))


def footprint_bounds(points: Tensor, K: Tensor, multiple: float) -> tuple[Tensor, Tensor]:
    """Per-pixel tangent bounds `multiple` times the pixel footprint: (g z / f_x, g z / f_y).

    points: [..., H, W, 3] camera-frame point map; K: [..., 3, 3]. A fronto-parallel plane's Sobel
    tangent is exactly z / f per pixel, so the bound is `multiple` pixels' worth of surface at that
    depth whatever the scene's units (the world bound of the paper is not: the same g makes surfels
    of far walls smaller than their pixels and lets near ones grow).
    """
    z = points[..., 2:].clamp_min(0)
    fx = K[..., 0, 0][..., None, None, None]
    fy = K[..., 1, 1][..., None, None, None]
    return multiple * z / fx, multiple * z / fy


class _InwardClamp(torch.autograd.Function):
    """clamp(x, lo, hi) whose gradient also passes where x is outside [lo, hi] and the gradient
    step (x - lr * grad) would move it towards the range; elsewhere outside, zero as a clamp's."""

    @staticmethod
    def forward(ctx, x: Tensor, lo: float, hi: float) -> Tensor:
        ctx.save_for_backward(x)
        ctx.bounds = (lo, hi)
        return x.clamp(lo, hi)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        (x,) = ctx.saved_tensors
        lo, hi = ctx.bounds
        passes = ((x >= lo) & (x <= hi)) | ((x < lo) & (grad < 0)) | ((x > hi) & (grad > 0))
        return torch.where(passes, grad, torch.zeros_like(grad)), None, None


def floor_scales(scales: Tensor, floor: Tensor, gradient: Literal["clamp", "inward"]) -> Tensor:
    """max(scales, floor) elementwise (floor: a detached tensor of the same shape), with the
    multipliers' gradient rule: "clamp" passes none below the floor, "inward" passes the gradients
    that would grow a surfel back over it."""
    if gradient == "inward":
        return _InwardClamp.apply(scales, floor, torch.full_like(floor, math.inf))
    return torch.maximum(scales, floor)


def clamp_multipliers(x: Tensor, lo: float, hi: float, gradient: Literal["clamp", "inward"]) -> Tensor:
    """Eq. 9's clamp of the scale multipliers; the values are the same for both gradient rules."""
    return _InwardClamp.apply(x, lo, hi) if gradient == "inward" else x.clamp(lo, hi)


# ---------------------------------------------------------------------------------------------- official
def release_sobel_tangents(points: Tensor) -> tuple[Tensor, Tensor]:
    """`sobel_tangents` computed the release's way: a grouped conv2d, then replicate padding.

    Same values as `sobel_tangents` in exact arithmetic. The filters subtract nearby points of
    similar size, so in float32 the result carries rounding of relative size ~1e-6 that depends on
    the summation order; only the same operation reproduces the release's rounding (on the golden
    case this keeps normals and covariances at ~1e-7 relative error instead of ~2e-6).
    points: [B, V, H, W, 3] -> (t1, t2), each [B, V, H, W, 3]
    """
    B, V, H, W, _ = points.shape
    x = rearrange(points, "b v h w c -> (b v) c h w")
    right = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=x.dtype, device=x.device) / 8
    out = []
    for kernel in (right, right.T):
        d = F.conv2d(x, kernel.expand(3, 1, 3, 3), groups=3)  # valid: [(B V), 3, H-2, W-2]
        d = F.pad(d, (1, 1, 1, 1), mode="replicate")
        out.append(rearrange(d, "(b v) c h w -> b v h w c", b=B))
    return out[0], out[1]


def release_rotation_from_normal(normals: Tensor) -> Tensor:
    """The release's rotation from a unit normal (NOT Rodrigues; exact only at 0 and 90 degrees).

    n' = n sign(n_z), v = e_z x n', c = n'_z, s = |v|, R = I + s [v]x + (1 - c) [v]x^2.
    normals: [..., 3] -> [..., 3, 3]
    """
    n = normals * torch.sign(normals[..., 2:])
    nx, ny, nz = n.unbind(-1)
    v = torch.stack((-ny, nx, torch.zeros_like(nx)), dim=-1)
    s = _safe_sqrt(v.square().sum(-1))
    V = skew(v)
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    return eye + V * s[..., None, None] + (V @ V) * (1 - nz)[..., None, None]


def release_quaternion_xyzw(R: Tensor) -> Tensor:
    """The release's quaternion of a matrix, (x, y, z, w) with w = sqrt(1 + trace) / 2, unnormalized.

    Valid for the release's matrices (their trace is >= 1). R: [..., 3, 3] -> [..., 4]
    """
    w = torch.sqrt(1 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]) / 2
    x = (R[..., 2, 1] - R[..., 1, 2]) / (4 * w)
    y = (R[..., 0, 2] - R[..., 2, 0]) / (4 * w)
    z = (R[..., 1, 0] - R[..., 0, 1]) / (4 * w)
    return torch.stack((x, y, z, w), dim=-1)


# ---------------------------------------------------------------------------------------------- adapter
class GaussianAdapter(torch.nn.Module):
    """Turns depth maps and raw head channels of V context views into world-frame Gaussians.

    No learnable parameters: it owns every activation, and the renderer receives physical quantities.
    """

    def __init__(self, cfg: AdapterConfig | None = None):
        super().__init__()
        self.cfg = cfg if cfg is not None else AdapterConfig()
        # Per-degree SH damping 0.1 * 0.25^l for l >= 1 (the release's), so at initialisation colour
        # is dominated by the DC term: [1, 0.025 x3, 0.00625 x5, ...]. Kept as Python floats and
        # made in the working dtype, so float64 runs get float64 constants.
        self.sh_mask_values = [1.0] + [
            0.1 * 0.25**l for l in range(1, self.cfg.sh_degree + 1) for _ in range(2 * l + 1)
        ]

    # ------------------------------------------------------------------ channel layout
    @property
    def num_scale_channels(self) -> int:
        return 3 if self.cfg.primitive == "gaussian3d" else 2

    @property
    def num_rotation_channels(self) -> int:
        return 4 if self.cfg.prior == "none" else 0

    @property
    def num_raw_channels(self) -> int:
        """Head channels per pixel: 32 for the default (1 + 2 + 2 + 3 * 9)."""
        return 3 + self.num_scale_channels + self.num_rotation_channels + 3 * num_sh_bases(self.cfg.sh_degree)

    def channel_slices(self) -> dict[str, slice]:
        """Where each quantity sits along the channel axis of `raw`."""
        s = 3 + self.num_scale_channels
        r = s + self.num_rotation_channels
        return {
            "opacity": slice(0, 1),
            "offset": slice(1, 3),
            "scale": slice(3, s),
            "rotation": slice(s, r),
            "sh": slice(r, self.num_raw_channels),
        }

    def alpha_threshold(self) -> float | None:
        """tau_alpha for the renderer's forced alpha normalization (Eq. 11); None when FAB is off."""
        if self.cfg.opacity_max >= 1.0:
            return None
        return self.cfg.alpha_threshold_train if self.training else self.cfg.alpha_threshold_eval

    # ------------------------------------------------------------------ forward
    def forward(
        self, depths: Tensor, raw: Tensor, images: Tensor, K: Tensor, c2w: Tensor, validate: bool = True
    ) -> AdapterOutput:
        """
        depths: [B, V, H, W] camera z
        raw:    [B, V, C, H, W] head output, C = num_raw_channels
        images: [B, V, 3, H, W] in [0, 1]
        K:      [B, V, 3, 3] intrinsics in pixels of the H x W maps
        c2w:    [B, V, 4, 4] OpenCV camera-to-world
        validate: check the values too (finite, pinhole K, rigid c2w: host reads; shapes always)
        """
        self._validate(depths, raw, images, K, c2w, validate)
        if self.cfg.mode == "official":
            return self._forward_official(depths, raw, images, K, c2w)
        return self._forward_paper(depths, raw, images, K, c2w)

    def _validate(self, depths: Tensor, raw: Tensor, images: Tensor, K: Tensor, c2w: Tensor, values: bool) -> None:
        check_tensor("depths", depths, ("B", "V", "H", "W"), finite=values)
        B, V, H, W = depths.shape
        check_tensor("raw", raw, (B, V, self.num_raw_channels, H, W), finite=values)
        check_tensor("images", images, (B, V, 3, H, W), finite=values)
        check_tensor("K", K, (B, V, 3, 3), finite=values)
        check_tensor("c2w", c2w, (B, V, 4, 4), finite=values)
        if values:
            validate_intrinsics("K", K.reshape(-1, 3, 3))
            validate_c2w("c2w", c2w.reshape(-1, 4, 4))
        if H < 3 or W < 3:
            raise SurfSplatInputError(f"depths: the surface prior needs maps of at least 3 x 3 pixels, got {H} x {W}")

    def _colour(self, raw_sh: Tensor, images: Tensor, R_c2w: Tensor, convention: SHConvention) -> Tensor:
        """SH in the world frame: raw [B, V, 3*K, H, W] -> [B, V, H, W, 3, K]."""
        # sh_mask_values made on the device from each coefficient's degree l = floor(sqrt(k)) (exact for
        # these small integers): 1 for l = 0, else 0.1 * 0.25^l. No table uploaded from the host.
        degree = torch.arange(len(self.sh_mask_values), device=raw_sh.device, dtype=raw_sh.dtype).sqrt().floor()
        mask = torch.where(degree == 0, 1.0, 0.1 * torch.pow(0.25, degree))
        sh = rearrange(raw_sh, "b v (c k) h w -> b v h w c k", c=3) * mask
        if self.cfg.init_sh_from_image:
            # Sec. 3.4: the input colour goes into the DC term, so SH(d) + 0.5 = rgb at initialisation.
            dc = rearrange(images, "b v c h w -> b v h w c") - 0.5
            sh = torch.cat((sh[..., :1] + (dc / SH_C0)[..., None], sh[..., 1:]), dim=-1)
        # The head predicts SH in the camera frame; rotate them into the world frame once per view.
        M = sh_rotation_matrix(R_c2w, self.cfg.sh_degree, convention)  # [B, V, K, K]
        return torch.einsum("bvij,bvhwcj->bvhwci", M, sh)

    def _forward_paper(self, depths: Tensor, raw: Tensor, images: Tensor, K: Tensor, c2w: Tensor) -> AdapterOutput:
        cfg = self.cfg
        ch = self.channel_slices()
        R_c2w = c2w[..., :3, :3]  # [B, V, 3, 3]
        # Forced alpha blending (Sec. 3.4): opacity bounded by tau_opa. The paper says "clip"; the
        # release scales a sigmoid, which is kept so that released weights mean the same thing.
        opacities = cfg.opacity_max * torch.sigmoid(raw[:, :, 0])  # [B, V, H, W]

        # Means: pixel centre + (sigmoid - 0.5) px, unprojected with camera z, then to the world.
        offsets = rearrange(torch.sigmoid(raw[:, :, ch["offset"]]) - 0.5, "b v c h w -> b v h w c")
        points_cam = unproject_depth(depths, K, offsets)  # [B, V, H, W, 3]
        means = torch.einsum("bvij,bvhwj->bvhwi", R_c2w, points_cam) + c2w[:, :, None, None, :3, 3]

        raw_scale = rearrange(raw[:, :, ch["scale"]], "b v c h w -> b v h w c")
        if cfg.prior == "surface":
            bounds = cfg.tangent_clamp
            if cfg.tangent_clamp_unit == "footprint":
                bounds = footprint_bounds(points_cam.detach(), K, cfg.tangent_clamp)
            frames = surface_frames(points_cam, bounds)
            rot_cam = frames.rotations
            r = cfg.scale_multiplier_range
            # Eq. 9's sigma-hat in [1/3, 3]
            multipliers = clamp_multipliers(F.softplus(raw_scale), 1 / r, r, cfg.multiplier_gradient)
            scales = frames.base_scales * multipliers[..., :2]  # Eq. 9
            if cfg.scale_floor is not None:
                floor = torch.cat(footprint_bounds(points_cam.detach(), K, cfg.scale_floor), dim=-1)
                scales = floor_scales(scales, floor, cfg.multiplier_gradient)
            if cfg.primitive == "gaussian3d":
                # No base scale exists along the normal; use the mean tangent scale, times its multiplier.
                thickness = frames.base_scales.mean(-1, keepdim=True) * multipliers[..., 2:]
                scales = torch.cat((scales, thickness), dim=-1)
            scales_mul = multipliers[..., :2]
        else:
            # DepthSplat's adapter: scales softplus(raw - 4), a normalized quaternion in the camera frame.
            scales = F.softplus(raw_scale - cfg.regressed_scale_shift)
            quats = rearrange(raw[:, :, ch["rotation"]], "b v c h w -> b v h w c")
            norm = quats.norm(dim=-1, keepdim=True)
            identity = torch.zeros_like(quats)
            identity[..., 0] = 1
            quats = torch.where(norm > 1e-8, quats / norm.clamp_min(1e-8), identity)
            rot_cam = quat_to_matrix(quats)
            scales_mul = torch.ones_like(scales[..., :2])

        if scales.shape[-1] == 2:
            scales = torch.cat((scales, torch.full_like(scales[..., :1], THIN_SCALE)), dim=-1)
        scales = scales.clamp(cfg.scale_min, cfg.scale_max)
        rot_world = R_c2w[:, :, None, None] @ rot_cam  # Eq. 5 in the world frame
        quats_world = matrix_to_quat(rot_world)
        sh = self._colour(raw[:, :, ch["sh"]], images, R_c2w, "3dgs")

        covariances = None
        if cfg.primitive == "gaussian3d":
            covariances = (rot_world * scales[..., None, :].square()) @ rot_world.transpose(-1, -2)
            covariances = _flatten(covariances, 2)

        gaussians = Gaussians(
            means=_flatten(means, 1),
            quats=_flatten(quats_world, 1),
            scales=_flatten(scales[..., :2], 1),
            opacities=_flatten(opacities, 0),
            sh=_flatten(sh, 2),
            explicit_covariances=covariances,
            validate=False,
        )
        return AdapterOutput(
            gaussians=gaussians,
            scales_mul=_flatten(scales_mul, 1),
            normals=_flatten(rot_world[..., :, 2], 1),
            scales=_flatten(scales, 1),
            rotations=_flatten(quats_world, 1),
        )

    def _forward_official(self, depths: Tensor, raw: Tensor, images: Tensor, K: Tensor, c2w: Tensor) -> AdapterOutput:
        """The release's SurfelAdapter, operation by operation (see golden/README.md)."""
        cfg = self.cfg
        B, V, H, W = depths.shape
        R_c2w = c2w[..., :3, :3]
        opacities = torch.sigmoid(raw[:, :, 0]) * cfg.opacity_max
        r = cfg.scale_multiplier_range
        scales_mul = rearrange(F.softplus(raw[:, :, 3:5]).clamp(1 / r, r), "b v c h w -> b v h w c")

        # The release works in image-normalized coordinates: pixel centres ((j+0.5)/W, (i+0.5)/H),
        # offsets (sigmoid - 0.5) / (W, H), intrinsics divided by the image size.
        scale_xy = torch.tensor([W, H, 1], dtype=K.dtype, device=K.device)
        K_norm = K / scale_xy[:, None]
        size = torch.tensor([W, H], dtype=depths.dtype, device=depths.device)
        xy = pixel_centers(H, W, depths.device, depths.dtype) / size
        pixel_size = 1 / size
        offsets = rearrange(torch.sigmoid(raw[:, :, 1:3]), "b v c h w -> b v h w c")
        xy = xy + (offsets - 0.5) * pixel_size
        homogeneous = torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)
        dirs = (torch.linalg.inv_ex(K_norm).inverse[:, :, None, None] @ homogeneous[..., None]).squeeze(-1)
        dirs = dirs / dirs[..., 2:]
        dirs = (R_c2w[:, :, None, None] @ dirs[..., None]).squeeze(-1)
        means = c2w[:, :, None, None, :3, 3] + dirs * depths[..., None]  # [B, V, H, W, 3] world

        # Sobel on WORLD-frame means (the paper uses the camera frame; identical when R_c2w = I).
        gx, gy = release_sobel_tangents(means)
        normals = F.normalize(torch.linalg.cross(gx, gy, dim=-1), dim=-1)
        rot = release_rotation_from_normal(normals)
        g = cfg.tangent_clamp
        gx, gy = gx.clamp(-g, g), gy.clamp(-g, g)
        # World X/Z and Y/Z components, whatever the camera's orientation.
        base = torch.stack(
            (_safe_sqrt(gx[..., 0] ** 2 + gx[..., 2] ** 2), _safe_sqrt(gy[..., 1] ** 2 + gy[..., 2] ** 2)), dim=-1
        )
        scales = base * scales_mul
        scales = torch.cat((scales, torch.full_like(scales[..., :1], cfg.scale_min)), dim=-1)
        scales = scales.clamp(cfg.scale_min, cfg.scale_max)
        S = torch.diag_embed(scales)
        covariances = rot @ S @ S.transpose(-1, -2) @ rot.transpose(-1, -2)
        # The camera rotation applied on top of a rotation already built from world normals.
        Rc = R_c2w[:, :, None, None]
        covariances = Rc @ covariances @ Rc.transpose(-1, -2)
        quats_xyzw = release_quaternion_xyzw(rot)
        sh = self._colour(raw[:, :, 5:], images, R_c2w, "e3nn")

        # Our Gaussians carry a proper rotation too: the (normalized) quaternion of R_c2w @ rot. It
        # only approximates the release's covariance (rot is not orthonormal); the explicit
        # covariance is the exact one and is what the EWA renderer uses.
        quats_wxyz = matrix_to_quat(Rc @ rot)
        gaussians = Gaussians(
            means=_flatten(means, 1),
            quats=_flatten(quats_wxyz, 1),
            scales=_flatten(scales[..., :2], 1),
            opacities=_flatten(opacities, 0),
            sh=_flatten(sh, 2),
            explicit_covariances=_flatten(covariances, 2),
            validate=False,
        )
        return AdapterOutput(
            gaussians=gaussians,
            scales_mul=_flatten(scales_mul, 1),
            normals=_flatten(normals, 1),
            scales=_flatten(scales, 1),
            rotations=_flatten(quats_xyzw, 1),
        )


def _flatten(x: Tensor, trailing: int) -> Tensor:
    """[B, V, H, W, *trail] -> [B, V*H*W, *trail] in (view, row, column) order."""
    return x.reshape(x.shape[0], -1, *x.shape[x.ndim - trailing :]) if trailing else x.reshape(x.shape[0], -1)
