"""Resize / crop / flip keep intrinsics exact: a 3D point lands on the same image content."""

from __future__ import annotations

import pytest
import torch

from surfsplat.data import center_crop, horizontal_flip, rescale_and_crop, resize_views
from surfsplat.utils.checks import SurfSplatInputError


def _project(K: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    p = X @ K.T
    return p[:, :2] / p[:, 2:]


def _edge_image(H: int, W: int, u0: float) -> torch.Tensor:
    """An image whose columns left of the continuous coordinate u0 are 0 and right are 1, with
    the boundary pixel holding its covered fraction (box-filtered), so resizing is exact in the mean."""
    u = torch.arange(W, dtype=torch.float64)
    frac = (u + 1 - u0).clamp(0, 1)
    return frac.expand(1, 3, H, W).clone()


@pytest.mark.parametrize("method", ["area", "bilinear", "lanczos"])
def test_resize_scales_intrinsics_about_the_pixel_corner(method: str) -> None:
    K = torch.tensor([[[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    X = torch.tensor([[0.37, -0.11, 2.0]], dtype=torch.float64)
    ((u, v),) = _project(K[0], X).tolist()
    img = _edge_image(48, 64, u)
    out, K2, _ = resize_views(img.float(), K, (12, 16), method=method)
    ((u2, v2),) = _project(K2[0], X).tolist()
    assert u2 == pytest.approx(u / 4) and v2 == pytest.approx(v / 4)
    # The edge in the resized image sits where the point now projects: the row sum of an image
    # that is 0 left of u' and 1 right of it equals W' - u'.
    if method == "area":
        assert float(out[0, 0, 0].sum()) == pytest.approx(16 - u2, abs=1e-5)


def test_center_crop_shifts_the_principal_point() -> None:
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 30, 40, generator=g)
    K = torch.tensor([[45.0, 0.0, 21.0], [0.0, 44.0, 14.0], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    out, K2, _ = center_crop(img, K, (20, 24))
    assert out.shape == (2, 3, 20, 24)
    X = torch.tensor([[0.1, 0.05, 1.0]])
    ((u, v),) = _project(K[0], X).tolist()
    ((u2, v2),) = _project(K2[0], X).tolist()
    # Crop offsets: rows (30 - 20) // 2 = 5, columns (40 - 24) // 2 = 8.
    assert (u - u2, v - v2) == pytest.approx((8.0, 5.0))
    assert torch.equal(out[0, :, int(v2), int(u2)], img[0, :, int(v), int(u)])


def test_rescale_and_crop_matches_the_release_geometry() -> None:
    img = torch.rand(1, 3, 360, 640)
    K = torch.tensor([[[400.0, 0.0, 320.0], [0.0, 400.0, 180.0], [0.0, 0.0, 1.0]]])
    depth = torch.rand(1, 1, 360, 640)
    out, K2, d2 = rescale_and_crop(img, K, (256, 256), method="bilinear", depths=depth)
    assert out.shape == (1, 3, 256, 256) and d2.shape == (1, 1, 256, 256)
    s = 256 / 360  # fits the height; width 455 (rounded), centre crop from column 99
    w_scaled = round(640 * s)
    col = (w_scaled - 256) // 2
    expected = torch.tensor([[400 * w_scaled / 640, 0, 320 * w_scaled / 640 - col], [0, 400 * s, 180 * s], [0, 0, 1]])
    torch.testing.assert_close(K2[0], expected)
    # Normalized by the output size this is the release's normalized K: fx * (w_scaled / 640) / 256.
    assert float(K2[0, 0, 0] / 256) == pytest.approx(400 / 640 * w_scaled / 256, rel=1e-6)


def test_horizontal_flip_mirrors_projections() -> None:
    g = torch.Generator().manual_seed(1)
    from surfsplat.geometry.cameras import look_at

    c2w = look_at(
        torch.tensor([[0.3, -2.0, 0.5]], dtype=torch.float64),
        torch.tensor([[0.0, 0.0, 0.2]], dtype=torch.float64),
        (0.0, 0.0, -1.0),
    )
    K = torch.tensor([[[60.0, 0.7, 30.0], [0.0, 58.0, 22.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    W = 64
    img = torch.rand(1, 3, 48, W, generator=g, dtype=torch.float64)
    out, c2w_f, K_f = horizontal_flip(img, c2w, K)
    X = torch.rand(5, 3, generator=g, dtype=torch.float64) * 0.5
    w2c = torch.linalg.inv(c2w[0])
    w2c_f = torch.linalg.inv(c2w_f[0])
    uv = _project(K[0], X @ w2c[:3, :3].T + w2c[:3, 3])
    Xm = X * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # the mirrored world
    uv_f = _project(K_f[0], Xm @ w2c_f[:3, :3].T + w2c_f[:3, 3])
    torch.testing.assert_close(uv_f[:, 0], W - uv[:, 0])
    torch.testing.assert_close(uv_f[:, 1], uv[:, 1])
    assert float(torch.linalg.det(c2w_f[0, :3, :3])) == pytest.approx(1.0)
    assert torch.equal(out[..., 0], img[..., -1])
    # Flipping twice is the identity.
    back = horizontal_flip(out, c2w_f, K_f)
    assert torch.equal(back[0], img) and torch.allclose(back[1], c2w) and torch.allclose(back[2], K)


def test_transform_errors() -> None:
    img = torch.rand(1, 3, 10, 10)
    K = torch.eye(3)[None]
    with pytest.raises(SurfSplatInputError, match=r"crop 12x4 \(HxW\) is larger than the images \(10x10\)"):
        center_crop(img, K, (12, 4))
    with pytest.raises(SurfSplatInputError, match="expected positive integer"):
        resize_views(img, K, (0, 5))
    with pytest.raises(SurfSplatInputError, match="method: expected one of"):
        resize_views(img, K, (5, 5), method="nearest")  # type: ignore[arg-type]
