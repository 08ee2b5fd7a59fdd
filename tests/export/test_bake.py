"""The export baked for standard 3DGS viewers (`surfsplat.export.bake`) against closed forms.

The surfels are what the real adapter makes of a plane at constant depth seen by one camera, with
the model's faint opacities (about 0.11, below the 0.14 median of the shipped model) and its
tangent-clamped scales (a third of a pixel): forced alpha blending shows the image, standard 3DGS
compositing (EWA, no normalisation, on black) a faint ghost of it. The bake runs on the compiled CPU
renderer; every figure is checked on the torch reference renderer in float64.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from surfsplat import Cameras
from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.export.bake import (
    COVERED_ALPHA,
    BakeConfig,
    bake_for_viewers,
    fit_cameras,
    thin_gaussians,
    viewer_figures,
)
from surfsplat.export.flow import ExportOptions, export_reconstruction
from surfsplat.export.ply import load_ply, save_ply
from surfsplat.model.adapter import GaussianAdapter
from surfsplat.render import render
from surfsplat.utils.checks import SurfSplatInputError

H = W = 24
FOCAL, DEPTH = 24.0, 4.0
FAINT = -1.5  # opacity logit: 0.6 * sigmoid(-1.5) = 0.11


def _camera() -> Cameras:
    K = torch.tensor([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]], dtype=torch.float64)
    return Cameras(torch.eye(4, dtype=torch.float64)[None], K[None])


def _plane(image: torch.Tensor):
    """The adapter's surfels for a plane at DEPTH showing `image` [3, H, W] to the one camera."""
    cams = _camera()
    adapter = GaussianAdapter().eval()
    raw = torch.zeros(1, 1, adapter.num_raw_channels, H, W, dtype=torch.float64)
    raw[:, :, 0] = FAINT
    depth = torch.full((1, 1, H, W), DEPTH, dtype=torch.float64)
    out = adapter(depth, raw, image[None, None], cams.K[None], cams.c2w[None])
    return out.gaussians.select(0), cams


def _texture() -> torch.Tensor:
    """Smooth colour waves of 8 and 12 pixels, a different phase per channel, within [0.15, 0.85]."""
    rows, cols = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    phase = torch.tensor([0.0, 2.1, 4.2], dtype=torch.float64)[:, None, None]
    return 0.5 + 0.2 * torch.sin(2 * math.pi * cols / 8 + phase) * torch.cos(2 * math.pi * rows / 12 + phase)


def _ours(g, cams, f: int):
    return render(g, cams.scaled(float(f)), W * f, H * f, backend="torch")


def _standard(g, cams, f: int):
    return render(g, cams.scaled(float(f)), W * f, H * f, mode="ewa", backend="torch", alpha_threshold=None)


def _covered_figures(std, ours) -> tuple[float, float]:
    """Mean standard alpha and colour PSNR over the pixels our render covers, written out here."""
    covered = ours.alpha[0, 0] >= COVERED_ALPHA
    mse = (std.color[0].clamp(0, 1) - ours.color[0].clamp(0, 1)).square().mean(0)[covered].mean()
    return float(std.alpha[0, 0][covered].mean()), float(-10 * torch.log10(mse))


@pytest.fixture(scope="module")
def baked_plane():
    g, cams = _plane(_texture())
    baked, report = bake_for_viewers(g, cams, H, W, backend="cpu")
    return g, cams, baked, report


def test_baked_textured_plane_composites_like_our_render(baked_plane):
    g, cams, baked, report = baked_plane
    for f in (1, 2):
        ours = _ours(g, cams, f)
        assert bool((ours.alpha >= COVERED_ALPHA).all())  # the plane fills the view
        # Unbaked, a standard viewer shows a ghost: the faint surfels cover a pixel to about 0.6.
        alpha, psnr = _covered_figures(_standard(thin_gaussians(g), cams, f), ours)
        assert alpha < 0.75 and psnr < 20
        # Baked: opaque, and the picture ours is.
        alpha, psnr = _covered_figures(_standard(baked, cams, f), ours)
        # (At x2 the plane's outermost half pixel is its Gaussians' fading edge.)
        assert alpha >= (0.99 if f == 1 else 0.98), f"x{f}: standard alpha {alpha:.4f}"
        assert psnr >= 35, f"x{f}: colour PSNR {psnr:.2f} dB"
        # The report's figures are these.
        assert report.after[f"context x{f}"].alpha == pytest.approx(alpha, abs=1e-6)
        assert report.after[f"context x{f}"].psnr == pytest.approx(psnr, abs=1e-3)
    # Our render of the plane is its texture (forced alpha blending undoes the faint opacities), so
    # the standard viewer shows the photo too.
    std = _standard(baked, cams, 1).color[0]
    assert float(-10 * torch.log10((std.clamp(0, 1) - _texture()).square().mean())) >= 30


def test_bake_keeps_positions_and_rotations_and_fits_the_rest(baked_plane):
    g, _, baked, report = baked_plane
    assert torch.equal(baked.means, g.means) and torch.equal(baked.quats, g.quats)
    assert baked.explicit_covariances is not None
    # Opacities leave the model's 0.6 cap; the third axis is thin next to the tangent ones.
    assert float(baked.opacities.median()) > 0.6 and float(g.opacities.max()) <= 0.6
    evals = torch.linalg.eigvalsh(baked.explicit_covariances)
    assert bool((evals[:, 0].sqrt() < 0.5 * evals[:, 1].sqrt()).all())
    assert report.best_step > 0 and report.fit_views == 1  # the context camera (BakeConfig: no extra views)
    assert len(report.losses) == report.steps == BakeConfig().steps_for(1) == 20  # one view: the fewest steps
    # Deterministic: the same bake twice is the same, bit for bit.
    again, _ = bake_for_viewers(g, _camera(), H, W, dataclasses.replace(BakeConfig(), steps=5), backend="cpu")
    once, _ = bake_for_viewers(g, _camera(), H, W, dataclasses.replace(BakeConfig(), steps=5), backend="cpu")
    assert torch.equal(again.explicit_covariances, once.explicit_covariances) and torch.equal(again.sh, once.sh)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_saturated_start_takes_the_weighted_alpha_from_one_backward_per_view(backend):
    # The start raises each opacity so that the pixels it covers reach the target alpha; the
    # alpha-weighted and plain blending-weight sums come from the red and green channels of one
    # backward pass, the same numbers as one backward pass for each (written out here).
    from surfsplat.export.bake import SH_C0, _saturated_logits

    g, cams = _plane(_texture())
    thin = thin_gaussians(g.to(torch.float64))
    config = BakeConfig()
    logits = _saturated_logits(thin, cams, W, H, config, backend)
    dc = torch.full_like(thin.sh[:, :1, :1], 0.5 / SH_C0).requires_grad_(True)
    probe = dataclasses.replace(thin, sh=dc.expand(-1, 3, -1), validate=False)
    out = render(probe, cams, W, H, mode="ewa", backend=backend, alpha_threshold=None)
    alpha = out.alpha.detach()
    (weighted,) = torch.autograd.grad((out.color[:, :1] * alpha).sum(), dc, retain_graph=True)
    (total,) = torch.autograd.grad(out.color[:, :1].sum(), dc)
    seen = total[:, 0, 0] > 1e-8
    assert int(seen.sum()) > H * W // 2
    pixel_alpha = (weighted[:, 0, 0] / total[:, 0, 0].clamp_min(1e-12)).clamp(1e-3, 1 - 1e-6)
    power = (math.log(1 - config.target_alpha) / torch.log1p(-pixel_alpha)).clamp_min(1.0)
    o = thin.opacities.clamp(1e-6, 1 - 1e-6)
    expected = torch.where(seen, -torch.expm1(power * torch.log1p(-o)), o).clamp(1e-4, config.target_alpha)
    assert torch.allclose(logits, torch.logit(expected), rtol=1e-12, atol=1e-12)
    assert float(torch.sigmoid(logits[seen]).mean()) > 2 * float(o[seen].mean())  # faint surfels raised


def test_viewer_figures_of_a_uniform_plane_in_closed_form():
    # One colour c everywhere: a standard viewer composites alpha * c on black, our render shows c
    # wherever alpha >= 0.001, so the PSNR over covered pixels is -10 log10(mean (1 - alpha)^2 mean_ch c^2).
    c = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64)
    g, cams = _plane(c[:, None, None].expand(3, H, W))
    ours = _ours(g, cams, 1)
    std = _standard(thin_gaussians(g), cams, 1)
    covered = ours.alpha[0, 0] >= COVERED_ALPHA
    a = std.alpha[0, 0][covered]
    expected = -10 * math.log10(float(((1 - a) ** 2).mean() * c.square().mean()))
    figures = viewer_figures(thin_gaussians(g), ours.color, ours.alpha, cams, W, H, backend="torch")
    assert figures.psnr == pytest.approx(expected, abs=1e-6)
    assert figures.alpha == pytest.approx(float(a.mean()), abs=1e-12)
    assert figures.covered == 1.0


def test_fit_cameras_interpolate_and_jitter_within_bounds():
    K = torch.tensor([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[1, 0, 3] = 1.0
    cams = Cameras(c2w, K.repeat(2, 1, 1))
    config = BakeConfig(nearby_views=3, jittered_views=2, jitter=0.05)
    probes = fit_cameras(cams, config, depth=4.0)
    assert len(probes) == 2 + 3 + 4
    assert torch.equal(probes.c2w[:2], c2w)
    # Interpolated: evenly between the two centres, same orientation.
    assert torch.allclose(probes.c2w[2:5, 0, 3], torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64))
    # Jittered copies of each context camera: moved by at most jitter * depth along each axis,
    # turned by at most sqrt(3) * jitter radians, and still rotations.
    jittered, base = probes.c2w[5:], c2w.repeat(2, 1, 1)
    assert bool(((jittered[:, :3, 3] - base[:, :3, 3]).abs() <= 0.05 * 4.0 + 1e-12).all())
    turn = base[:, :3, :3].transpose(1, 2) @ jittered[:, :3, :3]
    angle = torch.arccos(((turn.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))
    assert bool((angle <= math.sqrt(3) * 0.05 + 1e-9).all()) and bool((angle > 0).all())
    assert torch.allclose(turn @ turn.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3), atol=1e-12)
    assert torch.equal(fit_cameras(cams, config, depth=4.0).c2w, probes.c2w)  # seeded


def test_export_writes_the_model_output_exactly_and_the_viewer_ply_baked(tmp_path):
    g, cams = _plane(_texture())
    g = g.to(torch.float32)
    cams = Cameras(cams.c2w.float(), cams.K.float())
    options = ExportOptions(formats=("ply",), progress=False, bake=dataclasses.replace(BakeConfig(), steps=40))
    written = export_reconstruction(g, cams, W, H, tmp_path / "baked", options)
    # surfels.ply is the model's output, byte for byte.
    assert (tmp_path / "baked" / "surfels.ply").read_bytes() == save_ply(g, tmp_path / "model.ply").read_bytes()
    # surfels_3dgs.ply is baked: what a viewer reads from it composites opaque, and its JSON says so.
    viewer = load_ply(written["surfels (3DGS PLY, baked for viewers)"])
    ours = render(g, cams, W, H)
    std = render(viewer, cams, W, H, mode="ewa", alpha_threshold=None)
    record = json.loads(written["viewer bake figures"].read_text())
    alpha = float(std.alpha[ours.alpha >= COVERED_ALPHA].mean())
    assert alpha >= 0.99 and record["after"]["context x1"]["alpha"] == pytest.approx(alpha, abs=1e-4)
    assert record["before"]["context x1"]["alpha"] < 0.75
    # Without the bake: the thin surfels as they are, byte for byte.
    raw = export_reconstruction(g, cams, W, H, tmp_path / "raw", dataclasses.replace(options, bake=None))
    thin = save_ply(thin_gaussians(g), tmp_path / "thin.ply").read_bytes()
    assert raw["surfels (3DGS PLY, unbaked)"].read_bytes() == thin
    assert not (tmp_path / "raw" / "surfels_3dgs.json").exists()


def test_export_command_bakes_unless_raw_is_asked(tmp_path, capsys):
    g, cams = _plane(_texture())
    ply = save_ply(g, tmp_path / "surfels.ply")
    save_cameras(tmp_path / "cameras.json", cams, W, H, ["a.png"])
    argv = ["export", str(ply), "--cameras", str(tmp_path / "cameras.json"), "--formats", "ply"]
    assert main([*argv, "--out", str(tmp_path / "raw"), "--raw-3dgs"]) == 0
    assert "surfels (3DGS PLY, unbaked)" in capsys.readouterr().out
    thin = save_ply(thin_gaussians(load_ply(ply)), tmp_path / "thin.ply").read_bytes()
    assert (tmp_path / "raw" / "surfels_3dgs.ply").read_bytes() == thin
    assert main([*argv, "--out", str(tmp_path / "baked")]) == 0
    assert "surfels (3DGS PLY, baked for viewers)" in capsys.readouterr().out
    record = json.loads((tmp_path / "baked" / "surfels_3dgs.json").read_text())
    assert record["after"]["context x1"]["alpha"] >= 0.99 > 0.75 > record["before"]["context x1"]["alpha"]


def test_bake_steps_follow_the_fitted_views():
    """Six fits of each view, at least 20 steps; `steps` given wins."""
    config = BakeConfig()
    assert [config.steps_for(v) for v in (1, 2, 3, 4, 7, 18)] == [20, 20, 20, 24, 42, 108]
    assert dataclasses.replace(config, steps=5).steps_for(7) == 5
    assert dataclasses.replace(config, steps=0).steps_for(7) == 0
    assert dataclasses.replace(config, fits_per_view=2.5, min_steps=0).steps_for(3) == 8
    g, cams = _plane(_texture())
    three = Cameras(cams.c2w.expand(3, 4, 4), cams.K.expand(3, 3, 3))
    fast = dataclasses.replace(config, fits_per_view=2.0, min_steps=1, report_factors=(1,))
    _, report = bake_for_viewers(g, three, H, W, fast, backend="cpu")
    assert report.fit_views == 3 and report.steps == len(report.losses) == 6


def test_bake_errors():
    g, cams = _plane(_texture())
    bad_configs = ({"steps": -1}, {"factors": (0,)}, {"target_alpha": 1.0}, {"thickness": 0.0}, {"jitter": -0.1})
    for bad in (*bad_configs, {"fits_per_view": 0.0}, {"min_steps": -1}):
        with pytest.raises(SurfSplatInputError, match="bake"):
            BakeConfig(**bad)
    with pytest.raises(SurfSplatInputError, match="height and width"):
        bake_for_viewers(g, cams, 0, W)
    with pytest.raises(SurfSplatInputError, match="mode"):
        bake_for_viewers(g, cams, H, W, mode="splat")
    with pytest.raises(SurfSplatInputError, match="no Gaussians"):
        bake_for_viewers(g.subset(torch.zeros(len(g), dtype=torch.bool)), cams, H, W)


def test_bake_of_a_3dgs_layout_file_rendered_with_ewa():
    # A file read back from the 3DGS layout (explicit covariances) is ours to render with EWA and
    # forced alpha blending; the bake fits its standard compositing to that picture the same way.
    g, cams = _plane(_texture())
    g = thin_gaussians(g)
    baked, report = bake_for_viewers(g, cams, H, W, mode="ewa", backend="cpu")
    ours = render(g, cams, W, H, mode="ewa", backend="torch")
    alpha, psnr = _covered_figures(_standard(baked, cams, 1), ours)
    assert report.before["context x1"].alpha < 0.75
    assert alpha >= 0.99 and psnr >= 35, (alpha, psnr)
