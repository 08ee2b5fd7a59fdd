"""What each photo brings to a fit besides the scene: its exposure and its camera's error.

    views = PerView(PerViewConfig(appearance=True, cameras=True), cameras, extent)
    colour = views.expose(render(views.moved(surfels, v), cameras[v:v+1], ...).color, [v])

Two terms of the field's per-scene trainers, fitted with the scene and never part of it:

* Appearance (3DGS's exposure, `train_test_exp`; gsplat's `app_opt` is its learned-embedding cousin):
  each context photo v has an affine colour map, colour' = A_v colour + b_v, A_v [3, 3] and b_v [3]
  starting at the identity, applied to the render before the loss. Photos of one capture differ in
  exposure and white balance (a phone changes both from shot to shot); without the map the scene
  bakes each photo's exposure into view-dependent colour and floaters. The scene itself stays in no
  photo's exposure, so a held-out photo needs its own map: 3DGS fits it on the held-out photo's left
  half and scores the right half (its `train_test_exp` protocol). Here the left half's map is the
  closed-form least-squares fit (`held_out_exposure`): exact for the squared error, deterministic, no
  steps - 3DGS optimizes the same affine map by Adam in its training loop.
* Cameras (nerfstudio's camera optimizer "SO3xR3", gsplat's `pose_opt`, InstantSplat's joint
  optimization): each context camera v gets a correction E_v = [R(w_v) | t_v] in its own frame
  (axis-angle w_v, translation t_v in scene units, both starting at zero), the refined camera being
  c2w_v E_v. The gauge - the scene and every camera may move together - is fixed by holding the
  cameras of `fixed` (the first context view) where they are. The backends differentiate the surfels,
  not the cameras (the compiled CPU kernels and gsplat's 2DGS take cameras as constants), so view v is
  rendered with its camera as given and the surfels moved by the inverse, M_v = c2w_v E_v^-1 c2w_v^-1:
  the same image exactly (a rigid map of the world, the SH coefficients rotated with it by
  `rotate_sh`), and a gradient for w_v and t_v through plain torch ops on every backend. Held-out
  cameras of estimated poses then follow (`align_held_out`, test-time pose alignment as nerfstudio
  and InstantSplat evaluate): the scene frozen, each held-out correction fitted to its photo.

Rates: 3DGS's exposure rate, 0.01 decayed to 0.001; nerfstudio splatfacto's camera optimizer,
1e-4 decayed to 5e-7 (translations times the scene extent, nerfstudio's scenes being unit-sized).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras, rigid_inverse
from ..geometry.gaussians import Gaussians
from ..geometry.rotations import matrix_to_quat, skew
from ..geometry.sh_rotation import rotate_sh
from ..utils.checks import SurfSplatInputError


@dataclass(frozen=True)
class PerViewConfig:
    """Which per-photo terms a fit frees, and their Adam rates (first, last; decayed exponentially)."""

    appearance: bool = False  # an affine colour map per context photo (3DGS's exposure)
    appearance_rates: tuple[float, float] = (0.01, 0.001)  # 3DGS: exposure_lr_init, exposure_lr_final
    cameras: bool = False  # a rigid correction per context camera (for estimated poses)
    camera_rates: tuple[float, float] = (1e-4, 5e-7)  # nerfstudio splatfacto's camera optimizer
    fixed: tuple[int, ...] = (0,)  # context views whose cameras stay (the gauge)
    align_steps: int = 200  # held-out camera alignment: Adam steps per view (scene frozen)
    align_rate: float = 1e-3  # ... its rate (rotation in radians, translation times the extent)

    def __post_init__(self) -> None:
        for name in ("appearance_rates", "camera_rates"):
            first, last = getattr(self, name)
            if not (first > 0 and last > 0 and math.isfinite(first) and math.isfinite(last)):
                raise SurfSplatInputError(f"{name}: expected two positive rates, got {getattr(self, name)}")
        if self.align_steps < 0 or not self.align_rate > 0:
            raise SurfSplatInputError(
                f"align_steps/align_rate: expected steps >= 0 and a positive rate, got {self.align_steps}, "
                f"{self.align_rate}"
            )

    @property
    def active(self) -> bool:
        return self.appearance or self.cameras


def axis_angle_matrix(w: Tensor) -> Tensor:
    """Rodrigues: [..., 3] axis-angle -> [..., 3, 3], smooth at zero (the series below 1e-4 rad)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    theta = theta2.clamp_min(1e-30).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def correction(w: Tensor, t: Tensor) -> Tensor:
    """E = [R(w) | t] as [..., 4, 4] from axis-angle w [..., 3] and translation t [..., 3]."""
    E = torch.zeros(*w.shape[:-1], 4, 4, dtype=w.dtype, device=w.device)
    E[..., :3, :3] = axis_angle_matrix(w)
    E[..., :3, 3] = t
    E[..., 3, 3] = 1
    return E


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a b of (w, x, y, z) quaternions [..., 4] (R(a b) = R(a) R(b))."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def move_surfels(gaussians: Gaussians, M: Tensor) -> Gaussians:
    """The surfels under the rigid world map M [4, 4]: means, orientations and view-dependent colour."""
    R, t = M[:3, :3], M[:3, 3]
    means = gaussians.means @ R.T + t
    quats = quat_multiply(matrix_to_quat(R), gaussians.quats)  # R R(q) = R(q_R q), q's norm kept
    sh = gaussians.sh if gaussians.sh_degree == 0 else rotate_sh(gaussians.sh, R)
    return replace(gaussians, means=means, quats=quats, sh=sh, validate=False)


class PerView:
    """The per-photo tensors of one fit (see the module docstring) and their Adam."""

    def __init__(self, config: PerViewConfig, cameras: Cameras, extent: float) -> None:
        v, dtype, device = len(cameras), cameras.c2w.dtype, cameras.device
        self.config, self.cameras, self.extent = config, cameras, extent
        self.tensors: dict[str, Tensor] = {}
        if config.appearance:
            eye = torch.eye(3, 4, dtype=dtype, device=device)
            self.tensors["exposure"] = eye.repeat(v, 1, 1).requires_grad_(True)  # [V, 3, 4]
        if config.cameras:
            self.tensors["rotation"] = torch.zeros(v, 3, dtype=dtype, device=device, requires_grad=True)
            # in units of the extent, so one rate serves any scene size
            self.tensors["translation"] = torch.zeros(v, 3, dtype=dtype, device=device, requires_grad=True)
        self.free = torch.ones(v, 1, dtype=dtype, device=device)
        fixed = [i for i in config.fixed if i < v]
        self.free[fixed] = 0
        groups = [{"params": [p], "name": k} for k, p in self.tensors.items()]
        self.optimizer = torch.optim.Adam(groups, lr=1.0, eps=1e-15) if groups else None
        self.schedule(0.0)

    def schedule(self, done: float) -> None:
        if self.optimizer is None:
            return
        for group in self.optimizer.param_groups:
            first, last = self.config.appearance_rates if group["name"] == "exposure" else self.config.camera_rates
            group["lr"] = math.exp((1 - done) * math.log(first) + done * math.log(last))

    def zero_grad(self) -> None:
        if self.optimizer is not None:
            self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        if self.optimizer is not None:
            self.optimizer.step()

    def corrections(self, views: Tensor | list[int]) -> Tensor:
        """E_v [B, 4, 4] of the given views (identity where cameras are not refined or fixed)."""
        idx = torch.as_tensor(views, device=self.free.device)
        if not self.config.cameras:
            return torch.eye(4, dtype=self.free.dtype, device=self.free.device).expand(len(idx), 4, 4)
        w = self.tensors["rotation"][idx] * self.free[idx]
        t = self.tensors["translation"][idx] * self.free[idx] * self.extent
        return correction(w, t)

    def moved(self, gaussians: Gaussians, view: int) -> Gaussians:
        """The surfels as camera `view` as given sees them from its refined pose (identity: unchanged)."""
        if not self.config.cameras:
            return gaussians
        c2w = self.cameras.c2w[view]
        M = c2w @ rigid_inverse(self.corrections([view])[0]) @ rigid_inverse(c2w)
        return move_surfels(gaussians, M)

    def expose(self, colour: Tensor, views: Tensor | list[int]) -> Tensor:
        """colour [B, 3, H, W] of the given views through their exposure maps (unchanged without)."""
        if not self.config.appearance:
            return colour
        exposure = self.tensors["exposure"][torch.as_tensor(views, device=colour.device)]  # [B, 3, 4]
        return torch.einsum("bij,bjhw->bihw", exposure[:, :, :3], colour) + exposure[:, :, 3, None, None]

    def refined_cameras(self) -> Cameras:
        """The context cameras with their corrections applied (c2w_v E_v)."""
        with torch.no_grad():
            E = self.corrections(list(range(len(self.cameras))))
            return Cameras(self.cameras.c2w @ E, self.cameras.K, validate=False)

    def summary(self) -> dict:
        """Figures for the fit's stats: the largest correction and exposure change."""
        out: dict[str, float] = {}
        with torch.no_grad():
            if self.config.cameras:
                E = self.corrections(list(range(len(self.cameras))))
                cos = ((E[:, 0, 0] + E[:, 1, 1] + E[:, 2, 2] - 1) / 2).clamp(-1, 1)
                out["max_camera_rotation_deg"] = float(torch.rad2deg(torch.acos(cos)).max())
                out["max_camera_translation"] = float(E[:, :3, 3].norm(dim=-1).max())
            if self.config.appearance:
                eye = torch.eye(3, 4, dtype=self.free.dtype, device=self.free.device)
                out["max_exposure_change"] = float((self.tensors["exposure"] - eye).abs().max())
        return out


def held_out_exposure(render: Tensor, photo: Tensor) -> Tensor:
    """The affine colour map [3, 4] that takes `render` [3, H, W] closest to `photo` [3, H, W] in the
    squared error (least squares over the pixels; 3DGS's held-out exposure, in closed form)."""
    x = render.reshape(3, -1).T.double()  # [P, 3]
    y = photo.reshape(3, -1).T.double()
    design = torch.cat((x, torch.ones_like(x[:, :1])), 1)  # [P, 4]
    solution = torch.linalg.lstsq(design, y).solution  # [4, 3]: y = design @ solution
    return solution.T.to(render.dtype)  # [3, 4]


def exposure_protocol(renders: Tensor, photos: Tensor) -> tuple[Tensor, Tensor]:
    """3DGS's `train_test_exp` scoring of held-out views: each view's exposure map fitted on the left half
    of its photo (columns < W // 2), applied to the whole render; the score is taken on the right half.
    renders, photos [V, 3, H, W] -> (exposed renders [V, 3, H, W], right-half mask [1, 1, 1, W])."""
    half = renders.shape[-1] // 2
    exposed = []
    for render, photo in zip(renders, photos):
        A = held_out_exposure(render[..., :half], photo[..., :half])
        exposed.append(torch.einsum("ij,jhw->ihw", A[:, :3], render) + A[:, 3, None, None])
    right = torch.zeros(1, 1, 1, renders.shape[-1], dtype=torch.bool, device=renders.device)
    right[..., half:] = True
    return torch.stack(exposed), right


def align_held_out(
    draw,  # (surfels, cameras [1]) -> colour [1, 3, H, W], differentiable in the surfels
    gaussians: Gaussians,
    cameras: Cameras,  # [V] the held-out cameras as estimated
    photos: Tensor,  # [V, 3, H, W]
    extent: float,
    config: PerViewConfig,
) -> Cameras:
    """Held-out cameras fitted to their photos with the scene frozen (test-time pose alignment): per view,
    `config.align_steps` Adam steps on the squared colour error of a rigid correction, from zero; the
    correction of the lowest error seen is kept (zero when no step improved on the camera as given)."""
    frozen = gaussians.detach()
    c2ws = []
    for v in range(len(cameras)):
        w = torch.zeros(3, dtype=cameras.c2w.dtype, device=cameras.device, requires_grad=True)
        t = torch.zeros(3, dtype=cameras.c2w.dtype, device=cameras.device, requires_grad=True)
        optimizer = torch.optim.Adam([w, t], lr=config.align_rate, eps=1e-15)
        c2w = cameras.c2w[v]
        best = (math.inf, w.detach().clone(), t.detach().clone())
        for step in range(config.align_steps + 1):
            E = correction(w, t * extent)
            colour = draw(move_surfels(frozen, c2w @ rigid_inverse(E) @ rigid_inverse(c2w)), cameras[v : v + 1])
            loss = (colour - photos[v : v + 1]).square().mean()
            value = float(loss.detach())  # the loss of the parameters before this step's update
            if value < best[0]:
                best = (value, w.detach().clone(), t.detach().clone())
            if step == config.align_steps:
                break
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        c2ws.append(c2w @ correction(best[1], best[2] * extent))
    return Cameras(torch.stack(c2ws), cameras.K, validate=False)
