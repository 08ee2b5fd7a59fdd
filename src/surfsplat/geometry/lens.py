"""Camera lenses as COLMAP names them: the record every reader, pose estimation and the undistortion share.

A `Lens` is a camera model with its calibrated image size and its parameters in COLMAP's own order
(`colmap/src/colmap/sensor/models.h`; pycolmap's `Camera.params_info` prints them). Every stage after
loading sees pinhole cameras (SPEC section 2): a capture with a lens is undistorted once, where it is
read, and the reconstruction records the lens it came from beside the pinhole it used.

The math of the eleven models (ids 0-10) is COLMAP's, written here again in torch:
- `project` is COLMAP's `ImgFromCam` (with its cheirality check: points with z < machine epsilon
  give NaN), `unproject` its `CamFromImg`: the same closed forms, the same Newton iteration with
  the same trust region, step threshold and 100-iteration limit where COLMAP inverts a distortion
  iteratively (NaN where COLMAP's iteration does not converge), the fisheye models through the angle
  theta = atan(r) (COLMAP's `FisheyeFromNormal` / `NormalFromFisheye`, with their epsilon guards),
  FOV through its closed-form inverse with COLMAP's small-omega and small-radius series.
- Pixel coordinates are COLMAP's and this project's: the top-left pixel's centre is (0.5, 0.5).
- `undistorted_pinhole` is COLMAP's `UndistortCamera` with `image_undistorter`'s default options.
Why not call pycolmap: its `Camera` works on NumPy arrays on the host, one model at a time, in a
Python call per array; these functions take any leading batch shape, stay on the caller's device
and are differentiable where the closed forms are. pycolmap and OpenCV are their references in the
tests (`tests/geometry/test_lens.py`), to 1e-6 px.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError

# COLMAP's camera models: id -> (name, parameter names in COLMAP's order).
CAMERA_MODELS: dict[int, tuple[str, tuple[str, ...]]] = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
}
MODEL_IDS: dict[str, int] = {name: i for i, (name, _) in CAMERA_MODELS.items()}
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Models that apply their distortion to theta = atan(r) (COLMAP's BasePerspectiveFisheyeCameraModel).
FISHEYE_MODELS = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE")


@dataclass(frozen=True)
class Lens:
    """One camera's lens: COLMAP model name, the image size it was calibrated at, its parameters."""

    model: str  # a name of CAMERA_MODELS, e.g. "SIMPLE_RADIAL"
    width: int  # calibrated image size in pixels (of the stored pixels where orientation is not 1)
    height: int
    params: tuple[float, ...]  # in COLMAP's order for the model
    # EXIF orientation of the photos this lens sees (1: as read). Where it is 3, 6 or 8 the lens describes
    # the photos' STORED pixels (as COLMAP, nerfstudio and instant-ngp calibrate them) while the photos are
    # read as displayed: `undistort` takes a photo back to its stored pixels, undistorts it there and turns
    # the pinhole photo for display (see surfsplat.geometry.orientation). The projection functions here
    # take only stored-frame lenses (`stored()`).
    orientation: int = 1

    def __post_init__(self) -> None:
        if self.model not in MODEL_IDS:
            known = ", ".join(name for name, _ in CAMERA_MODELS.values())
            raise SurfSplatInputError(f"camera model: unknown model {self.model!r} (known: {known})")
        names = CAMERA_MODELS[MODEL_IDS[self.model]][1]
        if len(self.params) != len(names):
            raise SurfSplatInputError(
                f"camera model {self.model}: expected {len(names)} parameters ({', '.join(names)}), "
                f"got {len(self.params)}"
            )
        bad = [n for n, v in zip(names, self.params) if not math.isfinite(v)]
        if bad:
            raise SurfSplatInputError(f"camera model {self.model}: parameter {bad[0]} is NaN or inf")
        focal = [(n, v) for n, v in zip(names, self.params) if n in ("f", "fx", "fy")]
        if any(v <= 0 for _, v in focal):
            name, value = next((n, v) for n, v in focal if v <= 0)
            raise SurfSplatInputError(f"camera model {self.model}: focal length {name} is {value} (must be positive)")
        if self.width < 1 or self.height < 1:
            raise SurfSplatInputError(f"camera model {self.model}: size {self.width}x{self.height} is not positive")
        if self.orientation not in (1, 3, 6, 8) or isinstance(self.orientation, bool):
            raise SurfSplatInputError(
                f"camera model {self.model}: orientation must be an EXIF turn (1, 3, 6 or 8; a mirrored photo has "
                f"no camera), got {self.orientation!r}"
            )

    @property
    def param_names(self) -> tuple[str, ...]:
        return CAMERA_MODELS[MODEL_IDS[self.model]][1]

    @property
    def focal_and_centre(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels; models with one focal length "f" have fx = fy = f."""
        p = self.params
        if self.param_names[0] == "f":
            return p[0], p[0], p[1], p[2]
        return p[0], p[1], p[2], p[3]

    def intrinsics(self, dtype: torch.dtype = torch.float64) -> Tensor:
        """K [3, 3] in pixels (fx, fy, cx, cy; no skew): a pinhole's whole projection, a lens's linear part."""
        fx, fy, cx, cy = self.focal_and_centre
        return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)

    @property
    def extra_params(self) -> tuple[float, ...]:
        """The distortion parameters (COLMAP's extra_params), after focal length and principal point."""
        return self.params[3:] if self.param_names[0] == "f" else self.params[4:]

    @property
    def is_pinhole(self) -> bool:
        """Whether the model projects as a pinhole: a pinhole model, or a perspective model (FOV
        included) whose distortion parameters are all zero (fisheye models never are)."""
        if self.model in PINHOLE_MODELS:
            return True
        if self.model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "FOV"):
            # FOV with omega = 0 is COLMAP's exact pinhole (its series branch gives the factor 1)
            return all(v == 0 for v in self.extra_params)
        return False

    def rescaled(self, width: int, height: int) -> Lens:
        """The same lens for photos resized to width x height (COLMAP's `Camera::Rescale`): fx and cx
        scale by width's factor, fy and cy by height's, a single focal length f by their mean; the
        distortion parameters, on the normalized plane, stay."""
        sx, sy = width / self.width, height / self.height
        p = list(self.params)
        if self.param_names[0] == "f":
            p[0] *= 0.5 * (sx + sy)
            p[1] *= sx
            p[2] *= sy
        else:
            p[0], p[1], p[2], p[3] = p[0] * sx, p[1] * sy, p[2] * sx, p[3] * sy
        return Lens(self.model, width, height, tuple(p), self.orientation)

    def stored(self) -> Lens:
        """The lens of the stored pixels (orientation 1), which `project` and `unproject` take."""
        return Lens(self.model, self.width, self.height, self.params)

    def turned(self, orientation: int) -> Lens:
        """The same lens of the stored pixels, seeing photos displayed with this EXIF orientation."""
        return Lens(self.model, self.width, self.height, self.params, orientation)

    def to_dict(self) -> dict:
        out = {"model": self.model, "width": self.width, "height": self.height, "params": list(self.params)}
        if self.orientation != 1:
            out["orientation"] = self.orientation
        return out

    @classmethod
    def from_dict(cls, data: dict, source: str = "lens") -> Lens:
        try:
            orientation = data.get("orientation", 1)
            if not isinstance(orientation, int) or isinstance(orientation, bool):
                raise TypeError(f"orientation must be an integer, got {orientation!r}")
            return cls(
                str(data["model"]),
                int(data["width"]),
                int(data["height"]),
                tuple(float(v) for v in data["params"]),
                orientation,
            )
        except (KeyError, TypeError, ValueError) as err:
            raise SurfSplatInputError(
                f"{source}: a lens needs 'model', 'width', 'height' and 'params' ({type(err).__name__}: {err})"
            ) from None


# --- COLMAP's projection and its inverse -------------------------------------------------------

_EPS = 2.220446049250313e-16  # std::numeric_limits<double>::epsilon(), COLMAP's guards
# COLMAP's IterativeUndistortion (BasePerspectiveCameraModel): Newton's method with a trust region.
_NEWTON_ITERATIONS = 100
_NEWTON_MIN_STEP_SQ = 1e-10
_NEWTON_REL_RADIUS = 0.1
_NEWTON_RADIUS = 0.1
_FOV_EPS = 1e-4  # COLMAP's FOV model: "chosen arbitrarily", the switch to its series expansions


class _Jet:
    """A value with its derivatives by (u, v): ceres' Jet<double, 2>, as COLMAP differentiates the
    distortions in its Newton iteration. Only the arithmetic the polynomial and rational
    distortions use (+, -, *, /, with tensors and Python numbers)."""

    __slots__ = ("a", "du", "dv")

    def __init__(self, a: Tensor, du: Tensor | float, dv: Tensor | float) -> None:
        self.a, self.du, self.dv = a, du, dv

    @staticmethod
    def lift(x: _Jet | Tensor | float) -> _Jet:
        return x if isinstance(x, _Jet) else _Jet(x, 0.0, 0.0)

    def __add__(self, o: _Jet | Tensor | float) -> _Jet:
        o = _Jet.lift(o)
        return _Jet(self.a + o.a, self.du + o.du, self.dv + o.dv)

    __radd__ = __add__

    def __neg__(self) -> _Jet:
        return _Jet(-self.a, -self.du, -self.dv)

    def __sub__(self, o: _Jet | Tensor | float) -> _Jet:
        return self + (-_Jet.lift(o))

    def __rsub__(self, o: _Jet | Tensor | float) -> _Jet:
        return _Jet.lift(o) + (-self)

    def __mul__(self, o: _Jet | Tensor | float) -> _Jet:
        if not isinstance(o, _Jet):
            return _Jet(self.a * o, self.du * o, self.dv * o)
        return _Jet(self.a * o.a, self.du * o.a + self.a * o.du, self.dv * o.a + self.a * o.dv)

    __rmul__ = __mul__

    def __truediv__(self, o: _Jet | Tensor | float) -> _Jet:
        if not isinstance(o, _Jet):
            return _Jet(self.a / o, self.du / o, self.dv / o)
        q = self.a / o.a
        return _Jet(q, (self.du - q * o.du) / o.a, (self.dv - q * o.dv) / o.a)

    def __rtruediv__(self, o: _Jet | Tensor | float) -> _Jet:
        return _Jet.lift(o) / self


Distortion = Callable[[tuple[float, ...], Tensor, Tensor], tuple[Tensor, Tensor]]


def _radial_simple(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    # SIMPLE_RADIAL and SIMPLE_RADIAL_FISHEYE (on theta): k r^2
    radial = e[0] * (u * u + v * v)
    return u * radial, v * radial


def _radial(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    # RADIAL and RADIAL_FISHEYE (on theta): k1 r^2 + k2 r^4
    r2 = u * u + v * v
    radial = e[0] * r2 + e[1] * r2 * r2
    return u * radial, v * radial


def _opencv(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    k1, k2, p1, p2 = e
    u2, uv, v2 = u * u, u * v, v * v
    r2 = u2 + v2
    radial = k1 * r2 + k2 * r2 * r2
    return u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2), v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2)


def _opencv_fisheye(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    # applied to (u, v) = theta * direction: k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8
    k1, k2, k3, k4 = e
    t2 = u * u + v * v
    t4 = t2 * t2
    radial = k1 * t2 + k2 * t4 + k3 * t4 * t2 + k4 * t4 * t4
    return u * radial, v * radial


def _full_opencv(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    # OpenCV's rational model; COLMAP writes the displacement, hence the "- u", "- v"
    k1, k2, p1, p2, k3, k4, k5, k6 = e
    u2, uv, v2 = u * u, u * v, v * v
    r2 = u2 + v2
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    du = u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2) - u
    dv = v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2) - v
    return du, dv


def _thin_prism(e: tuple[float, ...], u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    k1, k2, p1, p2, k3, k4, sx1, sy1 = e
    u2, uv, v2 = u * u, u * v, v * v
    r2 = u2 + v2
    r4 = r2 * r2
    r6 = r4 * r2
    radial = k1 * r2 + k2 * r4 + k3 * r6 + k4 * r6 * r2
    du = u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2) + sx1 * r2
    dv = v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2) + sy1 * r2
    return du, dv


# The displacement (du, dv) each model adds on the normalized plane (or, fisheye, on the theta plane).
_DISTORTIONS: dict[str, Distortion] = {
    "SIMPLE_RADIAL": _radial_simple,
    "RADIAL": _radial,
    "OPENCV": _opencv,
    "FULL_OPENCV": _full_opencv,
    "OPENCV_FISHEYE": _opencv_fisheye,
    "SIMPLE_RADIAL_FISHEYE": _radial_simple,
    "RADIAL_FISHEYE": _radial,
    "THIN_PRISM_FISHEYE": _thin_prism,
}


def _fov_distort(omega: float, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """COLMAP's FOVCameraModel::Distortion: the distorted point itself (not a displacement)."""
    r2 = u * u + v * v
    omega2 = omega * omega
    if omega2 < _FOV_EPS:
        factor = (omega2 * r2) / 3 - omega2 / 12 + 1  # COLMAP's Taylor series in omega
    else:
        tan_half = math.tan(omega / 2)
        small = (-2 * tan_half * (4 * r2 * tan_half * tan_half - 3)) / (3 * omega)  # series in the radius
        radius = torch.sqrt(torch.where(r2 < _FOV_EPS, 1.0, r2))  # the unused branch kept finite (gradients)
        factor = torch.where(r2 < _FOV_EPS, small, torch.atan(radius * 2 * tan_half) / (radius * omega))
    return u * factor, v * factor


def _fov_undistort(omega: float, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """COLMAP's FOVCameraModel::Undistortion: its closed-form inverse."""
    r2 = u * u + v * v
    omega2 = omega * omega
    if omega2 < _FOV_EPS:
        factor = (omega2 * r2) / 3 - omega2 / 12 + 1
    else:
        tan_half = math.tan(omega / 2)
        small = (omega * (omega * omega * r2 + 3)) / (6 * tan_half)
        radius = torch.sqrt(torch.where(r2 < _FOV_EPS, 1.0, r2))
        factor = torch.where(r2 < _FOV_EPS, small, torch.tan(radius * omega) / (radius * 2 * tan_half))
    return u * factor, v * factor


def _fisheye_from_normal(u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """(u, v) on the normalized plane -> theta * direction (COLMAP's FisheyeFromNormal)."""
    r2 = u * u + v * v
    far = r2 > _EPS * _EPS  # COLMAP's r > eps; the other branch kept finite so gradients stay finite
    r = torch.sqrt(torch.where(far, r2, 1.0))
    scale = torch.where(far, torch.atan(r) / r, 1.0)
    return u * scale, v * scale


def _normal_from_fisheye(uu: Tensor, vv: Tensor) -> tuple[Tensor, Tensor]:
    """theta * direction -> the normalized plane (COLMAP's NormalFromFisheye). As COLMAP, a point at
    theta >= pi/2 (theta cos theta <= eps) is returned unscaled: such rays have no point on the plane."""
    t2 = uu * uu + vv * vv
    theta = torch.sqrt(torch.where(t2 > 0, t2, 1.0))
    t_cos = theta * torch.cos(theta)
    scaled = (t2 > 0) & (t_cos > _EPS)
    scale = torch.where(scaled, torch.sin(theta) / torch.where(scaled, t_cos, 1.0), 1.0)
    return uu * scale, vv * scale


def _iterative_undistortion(
    distortion: Distortion, e: tuple[float, ...], x0: Tensor, y0: Tensor
) -> tuple[Tensor, Tensor]:
    """COLMAP's IterativeUndistortion, vectorized: solve p + d(p) = p0 for p by Newton's method from
    p = p0, the step clipped to max(0.1 |p|, 0.1), converged when the step's squared norm < 1e-10;
    points not converged after 100 iterations are NaN (COLMAP returns false there). The Jacobian is
    exact (forward-mode derivatives of the distortion, `_Jet`, as COLMAP's ceres Jets)."""
    x, y = x0.clone(), y0.clone()
    active = torch.arange(x.numel(), device=x.device)
    xf, yf, x0f, y0f = x.view(-1), y.view(-1), x0.reshape(-1), y0.reshape(-1)
    converged = torch.zeros(x.numel(), dtype=torch.bool, device=x.device)

    for _ in range(_NEWTON_ITERATIONS):
        if active.numel() == 0:
            break
        a, b = xf[active], yf[active]
        ja, jb = distortion(e, _Jet(a, 1.0, 0.0), _Jet(b, 0.0, 1.0))
        j00, j01 = ja.du + 1, ja.dv
        j10, j11 = jb.du, jb.dv + 1
        r0 = a + ja.a - x0f[active]
        r1 = b + jb.a - y0f[active]
        det = j00 * j11 - j01 * j10
        s0 = (j11 * r0 - j01 * r1) / det
        s1 = (j00 * r1 - j10 * r0) / det
        radius_sq = torch.clamp(
            (a * a + b * b) * (_NEWTON_REL_RADIUS * _NEWTON_REL_RADIUS), min=_NEWTON_RADIUS * _NEWTON_RADIUS
        )
        step_sq = s0 * s0 + s1 * s1
        shrink = torch.where(step_sq > radius_sq, torch.sqrt(radius_sq / step_sq), torch.ones_like(step_sq))
        s0, s1 = s0 * shrink, s1 * shrink
        xf[active] = a - s0
        yf[active] = b - s1
        done = (s0 * s0 + s1 * s1) < _NEWTON_MIN_STEP_SQ
        converged[active[done]] = True
        active = active[~done]
    xf[~converged] = math.nan
    yf[~converged] = math.nan
    return x, y


def _float64(t: Tensor, last: int, name: str) -> Tensor:
    if not isinstance(t, Tensor) or t.ndim < 1 or t.shape[-1] != last:
        shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
        raise SurfSplatInputError(f"{name}: expected a tensor of shape [..., {last}], got {shape}")
    return t.to(torch.float64)


def _out_dtype(t: Tensor) -> torch.dtype:
    return t.dtype if t.is_floating_point() else torch.float64


def _of_stored_pixels(lens: Lens, name: str) -> None:
    """The projection is of the stored pixels: a lens seeing turned photos is a caller's mistake here."""
    if lens.orientation != 1:
        raise ValueError(
            f"{name}: the lens sees photos displayed with EXIF orientation {lens.orientation}; its projection is "
            "of their stored pixels: pass lens.stored()"
        )


def project(lens: Lens, points: Tensor) -> Tensor:
    """Points in the camera frame (OpenCV axes) -> pixels, COLMAP's `ImgFromCam` for `lens.model`.

    points: [..., 3]. Returns [..., 2] (x right, y down, top-left pixel centre at (0.5, 0.5)), in the
    points' floating dtype (computed in float64). Points with z < machine epsilon (at or behind the
    camera plane) give NaN, as pycolmap's `Camera.img_from_cam` with its default cheirality check.
    """
    p = _float64(points, 3, "project: points")
    w = p[..., 2]
    in_front = w >= _EPS
    w = torch.where(in_front, w, torch.ones_like(w))
    x, y = image_from_normalized(lens, p[..., 0] / w, p[..., 1] / w)
    out = torch.stack([x, y], dim=-1)
    out = torch.where(in_front[..., None], out, torch.full_like(out, math.nan))
    return out.to(_out_dtype(points))


def image_from_normalized(lens: Lens, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """`project` of the rays (u, v, 1), float64 tensors of shapes that broadcast (a row of columns
    and a column of rows make a grid without building it first): pixel x, pixel y."""
    _of_stored_pixels(lens, "project")
    fx, fy, cx, cy = lens.focal_and_centre
    model, e = lens.model, lens.extra_params
    if model == "FOV":
        x, y = _fov_distort(e[0], u, v)
    elif model in FISHEYE_MODELS:
        uu, vv = _fisheye_from_normal(u, v)
        du, dv = _DISTORTIONS[model](e, uu, vv)
        x, y = uu + du, vv + dv
    elif model in PINHOLE_MODELS:
        x, y = u, v
    else:
        du, dv = _DISTORTIONS[model](e, u, v)
        x, y = u + du, v + dv
    return fx * x + cx, fy * y + cy


def unproject(lens: Lens, pixels: Tensor) -> Tensor:
    """Pixels -> normalized image-plane coordinates (x/z, y/z), COLMAP's `CamFromImg`.

    pixels: [..., 2] (top-left pixel centre at (0.5, 0.5)). Returns [..., 2] in the pixels' floating
    dtype (computed in float64). Distortions without a closed-form inverse are inverted by COLMAP's
    Newton iteration (NaN where it does not converge, where pycolmap's `cam_from_img` gives NaN);
    fisheye models invert on theta and map back with tan(theta), and, as COLMAP, return the theta
    vector unscaled for a pixel whose ray is at 90 degrees or more from the axis. On an accelerator
    the iteration waits on the host twice per step (it stops, as COLMAP's, when every point has
    converged or after 100 steps); closed forms (pinhole, FOV) never wait.
    """
    _of_stored_pixels(lens, "unproject")
    q = _float64(pixels, 2, "unproject: pixels")
    fx, fy, cx, cy = lens.focal_and_centre
    x0 = (q[..., 0] - cx) / fx
    y0 = (q[..., 1] - cy) / fy
    model, e = lens.model, lens.extra_params
    if model in PINHOLE_MODELS:
        u, v = x0, y0
    elif model == "FOV":
        u, v = _fov_undistort(e[0], x0, y0)
    else:
        u, v = _iterative_undistortion(_DISTORTIONS[model], e, x0, y0)
        if model in FISHEYE_MODELS:
            u, v = _normal_from_fisheye(u, v)
    return torch.stack([u, v], dim=-1).to(_out_dtype(pixels))


# --- the pinhole a lens is undistorted to -----------------------------------------------------

_FOLD_SAMPLES = 64  # points on each segment from the axis to a border pixel's ray (the fold check)
_FOLD_RAYS = 512  # border pixels whose segments the fold check samples
_ROUND_TRIP_PX = 1e-4  # a converged inverse projects back within ~1e-9 px; beyond this the ray is wrong


def _border_pixels(width: int, height: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pixel centres UndistortCamera visits: left, right (every row), top, bottom (every column)."""
    ys = torch.arange(height, dtype=torch.float64) + 0.5
    xs = torch.arange(width, dtype=torch.float64) + 0.5
    left = torch.stack([torch.full_like(ys, 0.5), ys], dim=-1)
    right = torch.stack([torch.full_like(ys, width - 0.5), ys], dim=-1)
    top = torch.stack([xs, torch.full_like(xs, 0.5)], dim=-1)
    bottom = torch.stack([xs, torch.full_like(xs, height - 0.5)], dim=-1)
    return left, right, top, bottom


def _projection_jacobian_det(lens: Lens, rays: Tensor) -> Tensor:
    """det d(pixel)/d(x/z, y/z) of `project` at normalized points rays [N, 2], by central differences
    (step 1e-6: the fold check needs its sign, which they give far from zero)."""
    h = 1e-6
    one = torch.ones_like(rays[:, :1])

    def f(r: Tensor) -> Tensor:
        return project(lens, torch.cat([r, one], dim=-1))

    ex = torch.tensor([h, 0.0], dtype=torch.float64)
    ey = torch.tensor([0.0, h], dtype=torch.float64)
    da = (f(rays + ex) - f(rays - ex)) / (2 * h)
    db = (f(rays + ey) - f(rays - ey)) / (2 * h)
    return da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]


def _check_invertible(lens: Lens, border: Tensor, rays: Tensor) -> None:
    """Raise where the lens has no valid undistorted region (module docs of `undistorted_pinhole`)."""
    named = ", ".join(f"{n} {v:g}" for n, v in zip(lens.param_names, lens.params))
    what = f"camera model {lens.model} ({named}) at {lens.width}x{lens.height}"
    bad = ~torch.isfinite(rays).all(dim=-1)
    if lens.model in FISHEYE_MODELS and not bool(bad.any()):
        fx, fy, cx, cy = lens.focal_and_centre
        theta_vec = _iterative_undistortion(
            _DISTORTIONS[lens.model], lens.extra_params, (border[:, 0] - cx) / fx, (border[:, 1] - cy) / fy
        )
        theta = torch.sqrt(theta_vec[0] ** 2 + theta_vec[1] ** 2)
        beyond = theta * torch.cos(theta) <= _EPS
        if bool(beyond.any()):
            i = int(torch.nonzero(beyond)[0])
            raise SurfSplatInputError(
                f"{what}: no pinhole holds this lens: border pixel ({border[i, 0]:.1f}, {border[i, 1]:.1f}) sees "
                f"{math.degrees(float(theta[i])):.1f} degrees off the axis (90 or more)"
            )
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise SurfSplatInputError(
            f"{what}: no valid undistorted region: the distortion has no inverse at border pixel "
            f"({border[i, 0]:.1f}, {border[i, 1]:.1f}) (the lens map folds inside the image)"
        )
    back = project(lens, torch.cat([rays, torch.ones_like(rays[:, :1])], dim=-1))
    off = (back - border).norm(dim=-1)
    astray = ~(off <= _ROUND_TRIP_PX)
    if bool(astray.any()):
        i = int(torch.nonzero(astray)[0])
        raise SurfSplatInputError(
            f"{what}: no pinhole holds this lens: the ray of border pixel ({border[i, 0]:.1f}, {border[i, 1]:.1f}) "
            f"projects {float(off[i]):.3g} px away from it (the pixel sees 90 degrees or more off the axis)"
        )
    # the fold check on at most _FOLD_RAYS border pixels, evenly spaced (a fold is a smooth, radial
    # phenomenon: it spans many border pixels), corners included
    pick = torch.unique(torch.linspace(0, border.shape[0] - 1, min(border.shape[0], _FOLD_RAYS)).round().long())
    corners = torch.tensor([0, lens.height - 1, lens.height, 2 * lens.height - 1])
    pick = torch.unique(torch.cat([pick, corners]))
    t = torch.arange(1, _FOLD_SAMPLES + 1, dtype=torch.float64) / _FOLD_SAMPLES
    det = _projection_jacobian_det(lens, (t[:, None, None] * rays[pick][None]).reshape(-1, 2))
    det = det.reshape(_FOLD_SAMPLES, -1)
    folded = ~(det > 0).all(dim=0)
    if bool(folded.any()):
        i = int(pick[torch.nonzero(folded)[0]])
        raise SurfSplatInputError(
            f"{what}: no valid undistorted region: the lens map folds between the principal point and border "
            f"pixel ({border[i, 0]:.1f}, {border[i, 1]:.1f}) (its Jacobian determinant is not positive there)"
        )


def _div(a: float, b: float) -> float:
    """a / b in IEEE arithmetic, as COLMAP's C++ computes it (x / 0 is +-inf, 0 / 0 NaN; no exception)."""
    if b != 0:
        return a / b
    return math.nan if a == 0 or math.isnan(a) else math.copysign(math.inf, a) * math.copysign(1.0, b)


def undistorted_pinhole(lens: Lens) -> Lens:
    """The PINHOLE lens a photo of `lens` is undistorted to: COLMAP's `UndistortCamera` with the
    default options of `image_undistorter` (blank_pixels 0: the largest image without blank pixels;
    the scale of the size clamped to [min_scale 0.2, max_scale 2.0]; no ROI, no maximum size).

    The focal lengths are the lens's; the size is scaled (so it may change) and the principal point
    scaled with it. COLMAP lifts every border pixel centre of the distorted image to the normalized
    plane, projects it through the pinhole and picks the scale from the innermost of them.

    A lens that projects as a pinhole (`Lens.is_pinhole`) returns itself as PINHOLE, unchanged in
    size: no resampling is needed (COLMAP would still run its border search for a zero-distortion
    OPENCV camera and crop it by one pixel, an artefact of its asymmetric border formula).

    No valid region raises SurfSplatInputError naming the model and its parameters:
    - a border pixel whose distortion has no inverse (COLMAP's iteration does not converge: the
      distorted radius is beyond the largest the lens reaches, the map folds before the border);
    - a fisheye border pixel whose ray is 90 degrees or more off the axis (no pinhole image holds it;
      COLMAP's `NormalFromFisheye` returns a meaningless point there);
    - a border pixel whose lifted ray does not project back to it (FOV beyond 90 degrees: the
      closed-form inverse's tan() wraps to the opposite side);
    - a fold inside the image: the Jacobian determinant of the projection, sampled at 64 points on
      the segment from the axis to the rays of 512 border pixels evenly spaced along the border, the
      four corners included (these segments sweep the image's rays), is not positive somewhere (a
      second preimage: the inverse converged beyond a fold).
    """
    _of_stored_pixels(lens, "undistorted_pinhole")
    fx, fy, cx, cy = lens.focal_and_centre
    if lens.is_pinhole:
        return Lens("PINHOLE", lens.width, lens.height, (fx, fy, cx, cy))
    sides = _border_pixels(lens.width, lens.height)
    border = torch.cat(sides)
    rays = unproject(lens, border)
    _check_invertible(lens, border, rays)
    # ImgFromCam of the pinhole (fx, fy, cx, cy) at each lifted border point (all finite, checked above)
    x = fx * rays[:, 0] + cx
    y = fy * rays[:, 1] + cy
    n_rows, n_cols = lens.height, lens.width
    left_x, right_x = x[:n_rows], x[n_rows : 2 * n_rows]
    top_y, bottom_y = y[2 * n_rows : 2 * n_rows + n_cols], y[2 * n_rows + n_cols :]
    left_max_x, right_min_x = float(left_x.max()), float(right_x.min())
    top_max_y, bottom_min_y = float(top_y.max()), float(bottom_y.min())
    # scale such that there are no blank pixels (blank_pixels = 0 keeps only these two of COLMAP's four)
    max_scale_x = max(_div(cx, cx - left_max_x), _div(lens.width - 0.5 - cx, right_min_x - cx))
    max_scale_y = max(_div(cy, cy - top_max_y), _div(lens.height - 0.5 - cy, bottom_min_y - cy))
    scale_x = min(max(_div(1.0, max_scale_x), 0.2), 2.0)
    scale_y = min(max(_div(1.0, max_scale_y), 0.2), 2.0)
    width = int(max(1.0, scale_x * lens.width))  # C++'s static_cast<size_t>: truncation
    height = int(max(1.0, scale_y * lens.height))
    return Lens("PINHOLE", width, height, (fx, fy, cx * width / lens.width, cy * height / lens.height))
