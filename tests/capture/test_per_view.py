"""Per-photo terms of the fit (capture/per_view.py): the surfels moved by a camera correction render what
the corrected camera sees, the corrections' and exposure maps' gradients against finite differences, the
gauge held, a known exposure and a known camera error recovered by the fit, the held-out protocols."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

import surfsplat
from surfsplat.capture.fit import FitPlan, fit_on_views
from surfsplat.capture.per_view import (
    PerView,
    PerViewConfig,
    align_held_out,
    axis_angle_matrix,
    correction,
    exposure_protocol,
    held_out_exposure,
    move_surfels,
)
from surfsplat.geometry.cameras import Cameras, rigid_inverse
from surfsplat.geometry.sh import eval_sh
from surfsplat.render import render
from surfsplat.utils.checks import SurfSplatInputError

from .test_capture import SIZE, _two_views_of_a_textured_plane


def _view_dependent(plane: surfsplat.Gaussians) -> surfsplat.Gaussians:
    """The plane with degree-1 SH of its own, so a rotation of the world must rotate the colour field too."""
    g = torch.Generator().manual_seed(3)
    sh = torch.cat((plane.sh, 0.3 * torch.randn(len(plane), 3, 3, generator=g)), -1)
    return surfsplat.Gaussians(plane.means, plane.quats, plane.scales, plane.opacities, sh)


def test_axis_angle_matrix_is_rodrigues_and_smooth_at_zero():
    w = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    theta = float(w.norm())
    k = w / theta
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    expected = torch.eye(3, dtype=torch.float64) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K
    assert torch.allclose(axis_angle_matrix(w), expected, atol=1e-14)
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = axis_angle_matrix(zero)
    assert torch.equal(R.detach(), torch.eye(3, dtype=torch.float64))
    # d R / d w at zero is the skew map: R(e_i * eps) ~ I + eps [e_i]x
    (grad,) = torch.autograd.grad(R[2, 1], zero)  # R[2, 1] = w_x + O(w^2)
    assert torch.allclose(grad, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))


def test_moved_surfels_render_what_the_corrected_camera_sees():
    plane, cameras, _ = _two_views_of_a_textured_plane()
    plane = _view_dependent(plane)
    E = correction(torch.tensor([0.02, -0.015, 0.01]), torch.tensor([0.03, -0.02, 0.05]))
    c2w = cameras.c2w[1]
    corrected = Cameras((c2w @ E)[None], cameras.K[1:2])
    M = c2w @ rigid_inverse(E) @ rigid_inverse(c2w)
    direct = render(plane, corrected, SIZE, SIZE, backend="torch")
    moved = render(move_surfels(plane, M), cameras[1], SIZE, SIZE, backend="torch")
    for name in ("color", "alpha", "depth"):
        assert torch.allclose(getattr(direct, name), getattr(moved, name), atol=2e-5), name
    # the view-dependent colour followed: the moved SH evaluated along R d equal the originals along d
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -0.4, 0.8]]), dim=-1)
    original = eval_sh(plane.sh[:1], d)
    rotated = eval_sh(move_surfels(plane, M).sh[:1], d @ M[:3, :3].T)
    assert torch.allclose(original, rotated, atol=1e-5)


def _views(config: PerViewConfig, cameras: Cameras) -> PerView:
    return PerView(config, cameras.to(torch.float64), extent=1.0)


def test_camera_and_exposure_gradients_match_finite_differences():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    plane = _view_dependent(plane).to(torch.float64)
    cameras, photos = cameras.to(torch.float64), photos.double()
    views = _views(PerViewConfig(appearance=True, cameras=True, fixed=()), cameras)
    with torch.no_grad():  # away from the identity, where the loss is not flat
        views.tensors["rotation"][1] = torch.tensor([0.01, -0.02, 0.015])
        views.tensors["translation"][1] = torch.tensor([0.02, 0.01, -0.03])
        views.tensors["exposure"][1] += 0.05 * torch.arange(12, dtype=torch.float64).reshape(3, 4) / 12
    target = photos[1:2] * 0.9 + 0.05

    def loss() -> torch.Tensor:
        out = render(views.moved(plane, 1), cameras[1], SIZE, SIZE, backend="torch")
        return (views.expose(out.color, [1]) - target).square().mean()

    value = loss()
    value.backward()
    for name, index in (("rotation", (1, 0)), ("rotation", (1, 2)), ("translation", (1, 1)), ("exposure", (1, 0, 3))):
        tensor = views.tensors[name]
        analytic = float(tensor.grad[index])
        # the render's per-pixel cut-offs (alpha 1/255, the low-pass switch) make the loss piecewise smooth:
        # a difference over 1e-4 crosses some of them, one over 1e-7 none here
        eps = 1e-7
        with torch.no_grad():
            tensor[index] += eps
            up = float(loss())
            tensor[index] -= 2 * eps
            down = float(loss())
            tensor[index] += eps
        numeric = (up - down) / (2 * eps)
        assert analytic == pytest.approx(numeric, rel=1e-5, abs=1e-9), (name, index, analytic, numeric)


def test_fixed_views_hold_the_gauge():
    _, cameras, _ = _two_views_of_a_textured_plane()
    views = _views(PerViewConfig(cameras=True, fixed=(0,)), cameras)
    with torch.no_grad():
        views.tensors["rotation"] += 0.1
        views.tensors["translation"] += 0.1
    E = views.corrections([0, 1])
    assert torch.equal(E[0], torch.eye(4, dtype=torch.float64))
    assert not torch.allclose(E[1], torch.eye(4, dtype=torch.float64))
    refined = views.refined_cameras()
    assert torch.equal(refined.c2w[0], cameras.c2w[0].double())


def test_held_out_exposure_recovers_an_affine_map_and_the_protocol_scores_the_right_half():
    g = torch.Generator().manual_seed(0)
    render_ = torch.rand(3, 20, 30, generator=g)
    A = torch.tensor([[0.9, 0.05, 0.0, 0.02], [0.0, 1.1, 0.03, -0.01], [0.02, 0.0, 0.8, 0.05]])
    photo = torch.einsum("ij,jhw->ihw", A[:, :3], render_) + A[:, 3, None, None]
    assert torch.allclose(held_out_exposure(render_, photo), A, atol=1e-5)
    # fitted on the left half only: a photo whose right half differs is not fitted there
    photo_b = photo.clone()
    photo_b[..., 15:] += 0.2
    exposed, right = exposure_protocol(render_[None], photo_b[None])
    assert torch.allclose(exposed[0, ..., :15], photo[..., :15], atol=1e-5)
    assert torch.allclose(exposed[0, ..., 15:] + 0.2, photo_b[..., 15:], atol=1e-5)
    assert right.sum() == 15 and bool(right[..., 15:].all())


def _exposed_photos(plane, cameras):
    """Renders of the plane through two known exposure maps (the second view's a different exposure)."""
    photos = render(plane, cameras, SIZE, SIZE).color
    maps = torch.stack(
        (torch.eye(3, 4), torch.tensor([[1.15, 0.0, 0.0, -0.03], [0.0, 1.1, 0.0, 0.02], [0.0, 0.0, 0.9, 0.04]]))
    )
    exposed = torch.einsum("vij,vjhw->vihw", maps[:, :, :3], photos) + maps[:, :, 3, None, None]
    return exposed.clamp(0, 1), maps


def test_fit_with_appearance_recovers_a_photo_exposure_and_the_scene_stays_in_the_first():
    plane, cameras, _ = _two_views_of_a_textured_plane()
    photos, maps = _exposed_photos(plane, cameras)
    plan = FitPlan(
        name="optimize",
        steps=150,
        rates={"sh_dc": 2e-3},
        views_per_step=2,
        per_view=PerViewConfig(appearance=True, appearance_rates=(2e-2, 2e-3)),
    )
    out: dict = {}
    fitted, stats = fit_on_views(plane, cameras, photos, SIZE, SIZE, plan, per_view_out=out)
    assert stats["kept"] == 1.0 and out["exposure"] is not None
    without, stats_plain = fit_on_views(plane, cameras, photos, SIZE, SIZE, replace_plan(plan, per_view=None))
    # the exposure maps explain the photos' difference: the colour error is far below the plain fit's
    assert stats["mse_after"] < 0.2 * stats_plain["mse_after"], (stats["mse_after"], stats_plain["mse_after"])
    # relative to the first photo's map, the second's is the known one
    A0, A1 = (torch.cat((m, torch.tensor([[0.0, 0, 0, 1]]))) for m in out["exposure"].float())
    relative = (A1 @ torch.linalg.inv(A0))[:3]
    assert torch.allclose(relative, maps[1], atol=0.03), relative


def replace_plan(plan: FitPlan, **changes) -> FitPlan:
    from dataclasses import replace

    return replace(plan, **changes)


def _two_depths(plane: surfsplat.Gaussians, cameras: Cameras) -> surfsplat.Gaussians:
    """The plane's right half pushed back along the first camera's rays by a quarter: a scene of two
    depths, which fixes a camera's pose (a single plane trades rotation for translation). Each surfel's
    depth is also jittered by up to 1 %: on the plane every surfel has one depth, and the order of equal
    depths - which overlapping surfel is in front - would flip with the last bit of a camera."""
    centre = cameras.c2w[0, :3, 3]
    jitter = 1 + 0.01 * torch.rand(len(plane), generator=torch.Generator().manual_seed(5))
    push = (torch.where(plane.means[:, 0] > plane.means[:, 0].median(), 1.25, 1.0) * jitter)[:, None]
    means = centre + (plane.means - centre) * push
    return surfsplat.Gaussians(means, plane.quats, plane.scales * push, plane.opacities, plane.sh)


def test_fit_with_camera_refinement_recovers_a_camera_error():
    plane, cameras, _ = _two_views_of_a_textured_plane()
    plane = _two_depths(plane, cameras)
    photos = render(plane, cameras, SIZE, SIZE).color
    # the second camera as estimated: 0.6 degrees and 1 cm off the camera that made its photo
    E = correction(torch.tensor([0.0, 0.0105, 0.0]), torch.tensor([0.01, 0.0, 0.0]))
    wrong = Cameras(torch.stack((cameras.c2w[0], cameras.c2w[1] @ rigid_inverse(E))), cameras.K)
    plan = FitPlan(
        name="optimize",
        steps=200,
        rates={"sh_dc": 1e-9},  # the scene is right: only the camera has to move
        views_per_step=2,
        extent=1.0,
        per_view=PerViewConfig(cameras=True, camera_rates=(5e-4, 5e-5)),
    )
    out: dict = {}
    _, stats = fit_on_views(plane, wrong, photos, SIZE, SIZE, plan, backend="torch", per_view_out=out)
    assert stats["kept"] == 1.0
    refined = out["cameras"]
    assert torch.equal(refined.c2w[0], wrong.c2w[0])  # the gauge

    before, after = _pose_error(cameras.c2w[1], wrong.c2w[1]), _pose_error(cameras.c2w[1], refined.c2w[1])
    assert after[0] < 0.25 * before[0] and after[1] < 0.5 * before[1], (before, after)


def test_camera_refinement_hands_absgs_its_absolute_screen_gradients():
    """With camera refinement each view renders the surfels moved by its correction; AbsGS's densification
    must still get the render's absolute screen gradients (the shipped strategy with estimated cameras).
    Corrections held at the identity (rates of 1e-12) densify as the fit without them does."""
    from surfsplat.capture.densify import DensifyConfig

    plane, cameras, _ = _two_views_of_a_textured_plane()
    photos = render(plane, cameras, SIZE, SIZE).color
    shifted = surfsplat.Gaussians(
        plane.means + 0.01, plane.quats, plane.scales * 1.5, plane.opacities, plane.sh
    )  # a start to fit, so the screen gradients are not zero
    densify = DensifyConfig(start=0.0, stop=1.0, every=10, absgrad=True, abs_grad_threshold=1e-6)
    histories = []
    for per_view in (None, PerViewConfig(cameras=True, camera_rates=(1e-12, 1e-12))):
        plan = FitPlan(name="optimize", steps=30, rates={"means": 1e-4, "quats": 1e-3, "log_scales": 5e-3,
                       "logits": 0.05, "sh_dc": 2.5e-3, "sh_rest": 1.25e-4}, views_per_step=1, extent=1.0,
                       densify=densify, per_view=per_view)  # fmt: skip
        _, stats = fit_on_views(shifted, cameras, photos, SIZE, SIZE, plan, backend="torch", per_view_out={})
        histories.append([(h["cloned"], h["split"], h["pruned"]) for h in stats["densify"]])
    assert len(histories[0]) == 3 and sum(c + s for c, s, _ in histories[0]) > 0  # it grew
    assert histories[1] == histories[0]


def _pose_error(truth: Tensor, c2w: Tensor) -> tuple[float, float]:
    """(degrees, distance) between two camera-to-world matrices."""
    delta = rigid_inverse(truth.double()) @ c2w.double()
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(delta[:3, :3].trace()) - 1) / 2))))
    return angle, float(delta[:3, 3].norm())


def test_held_out_alignment_moves_a_wrong_camera_back_and_keeps_a_right_one():
    plane, cameras, _ = _two_views_of_a_textured_plane()
    plane = _two_depths(plane, cameras)
    photos = render(plane, cameras, SIZE, SIZE).color
    E = correction(torch.tensor([0.0, 0.0105, 0.0]), torch.tensor([0.01, 0.0, 0.0]))
    wrong = Cameras(cameras.c2w[1:] @ rigid_inverse(E), cameras.K[1:])

    def draw(surfels, cams):
        return render(surfels, cams, SIZE, SIZE).color

    config = PerViewConfig(cameras=True, align_steps=80, align_rate=5e-4)
    aligned = align_held_out(draw, plane, wrong, photos[1:], 1.0, config)
    before = float((draw(plane, wrong) - photos[1:]).square().mean())
    after = float((draw(plane, aligned) - photos[1:]).square().mean())
    assert after < 0.5 * before, (before, after)
    error_before, error_after = _pose_error(cameras.c2w[1], wrong.c2w[0]), _pose_error(cameras.c2w[1], aligned.c2w[0])
    assert error_after[0] < 0.5 * error_before[0], (error_before, error_after)
    right = align_held_out(draw, plane, cameras[1:], photos[1:], 1.0, config)  # already right: stays
    assert torch.allclose(right.c2w, cameras.c2w[1:], atol=1e-6)


def test_per_view_config_refuses_bad_rates():
    with pytest.raises(SurfSplatInputError, match="appearance_rates"):
        PerViewConfig(appearance_rates=(0.0, 1e-3))
    with pytest.raises(SurfSplatInputError, match="align_steps"):
        PerViewConfig(align_steps=-1)
