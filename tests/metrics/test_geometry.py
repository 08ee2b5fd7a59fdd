"""Geometry metrics against closed forms: depth offsets, rotated normals, offset point sets, DTU's protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from scipy.io import savemat

from surfsplat.metrics.dtu import (
    downsample,
    dtu_chamfer,
    dtu_chamfer_mesh,
    load_dtu_reference,
    sample_mesh_dtu,
)
from surfsplat.metrics.geometry import (
    angular_error_deg,
    normal_metrics,
    normalize_by_alpha,
    sample_mesh,
    surface_metrics,
    view_geometry,
)
from surfsplat.utils.checks import SurfSplatInputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _rotate_x(vectors: torch.Tensor, degrees: float) -> torch.Tensor:
    """vectors [..., 3] rotated about the x axis."""
    a = math.radians(degrees)
    R = torch.tensor(
        [[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]], dtype=torch.float64
    )
    return vectors @ R.T


# ------------------------------------------------------------------------------------------- per view
def test_depth_of_an_offset_plane_has_the_closed_form_errors():
    # A fronto-parallel plane at depth D rendered at D + e: AbsRel = e / D, RMSE = e, delta1 = 1 (ratio < 1.25).
    D, e = 2.0, 0.3
    true_depth = torch.full((2, 1, 8, 8), D, dtype=torch.float64)
    normal = torch.zeros(2, 3, 8, 8, dtype=torch.float64)
    normal[:, 2] = -1.0
    out = view_geometry(
        true_depth + e, normal, torch.ones(2, 1, 8, 8), true_depth, normal, torch.ones(2, 1, 8, 8, dtype=torch.bool)
    )
    m = out.mean()
    assert m["abs_rel"] == pytest.approx(e / D, abs=1e-12)
    assert m["rmse"] == pytest.approx(e, abs=1e-12)
    assert m["delta1"] == 1.0
    assert m["mean_deg"] == 0.0 and m["coverage"] == 1.0
    # Depth 1.3 D is a ratio above 1.25: every pixel fails delta1.
    far = view_geometry(
        true_depth * 1.3, normal, torch.ones(2, 1, 8, 8), true_depth, normal, torch.ones(2, 1, 8, 8, dtype=torch.bool)
    )
    assert far.mean()["delta1"] == 0.0 and far.mean()["abs_rel"] == pytest.approx(0.3)


def test_rotated_normals_give_the_rotation_angle():
    truth = torch.nn.functional.normalize(torch.randn(1, 4, 5, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    truth = truth.double()
    # Rotating about the x axis turns a vector by the angle only if it is perpendicular to x.
    truth[..., 0] = 0.0
    truth = torch.nn.functional.normalize(truth, dim=-1)
    for degrees in (0.5, 15.0, 25.0, 90.0, 179.0):
        pred = _rotate_x(truth, degrees)
        m = normal_metrics(pred.permute(0, 3, 1, 2), truth.permute(0, 3, 1, 2)).mean()
        assert m["mean_deg"] == pytest.approx(degrees, abs=1e-9)
        assert m["median_deg"] == pytest.approx(degrees, abs=1e-9)
        assert m["within_11_25"] == float(degrees < 11.25)
        assert m["within_22_5"] == float(degrees < 22.5)
        assert m["within_30"] == float(degrees < 30.0)


def test_normal_shares_mean_and_median_of_a_known_mix():
    # Five pixels: three off by 5 deg, two by 25 deg -> mean 13, median 5, shares 3/5, 3/5, 1.
    truth = torch.zeros(1, 5, 3, dtype=torch.float64)
    truth[..., 2] = 1.0
    pred = torch.cat([_rotate_x(truth[:, :3], 5.0), _rotate_x(truth[:, 3:], 25.0)], dim=1)
    m = normal_metrics(pred.permute(0, 2, 1)[..., None], truth.permute(0, 2, 1)[..., None]).mean()
    assert m["mean_deg"] == pytest.approx(13.0, abs=1e-9)
    assert m["median_deg"] == pytest.approx(5.0, abs=1e-9)
    assert (m["within_11_25"], m["within_22_5"], m["within_30"]) == (0.6, 0.6, 1.0)


def test_normal_error_ignores_length_and_a_zero_prediction_is_180_degrees():
    a = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert angular_error_deg(a, b).tolist() == pytest.approx([0.0, 180.0, 90.0], abs=1e-12)


def test_view_geometry_scores_only_masked_opaque_pixels_and_reports_coverage():
    truth_depth = torch.full((1, 1, 4, 4), 2.0)
    normal = torch.zeros(1, 3, 4, 4)
    normal[:, 2] = -1.0
    depth = truth_depth.clone()
    depth[..., 0, :] = 100.0  # wrong, but transparent: not scored
    alpha = torch.ones(1, 1, 4, 4)
    alpha[..., 0, :] = 0.05
    mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
    mask[..., 3, :] = False  # a row the context views never saw: neither scored nor counted in coverage
    depth[..., 3, :] = 50.0
    out = view_geometry(depth, normal, alpha, truth_depth, normal, mask, min_alpha=0.1)
    assert out.depth.num_valid.tolist() == [8]
    assert out.mean()["abs_rel"] == 0.0
    assert out.coverage.tolist() == [pytest.approx(8 / 12)]
    # Nothing to score in a view: NaN there, and the mean refuses rather than inventing a number.
    empty = view_geometry(depth, normal, alpha, truth_depth, normal, torch.zeros_like(mask))
    assert math.isnan(float(empty.coverage[0]))
    with pytest.raises(SurfSplatInputError, match="no image has a valid"):
        empty.mean()


def test_normalize_by_alpha_recovers_the_weighted_mean():
    depth = torch.tensor([[[[0.6, 0.01]]]])
    alpha = torch.tensor([[[[0.3, 0.02]]]])
    out = normalize_by_alpha(depth, alpha, 0.1)
    assert out.flatten().tolist() == pytest.approx([2.0, 0.0])


def test_view_geometry_rejects_bad_input():
    d = torch.ones(1, 1, 4, 4)
    n = torch.zeros(1, 3, 4, 4)
    with pytest.raises(SurfSplatInputError, match="mask: expected a bool"):
        view_geometry(d, n, d, d, n, torch.ones(1, 1, 4, 4))
    with pytest.raises(SurfSplatInputError, match="normal"):
        view_geometry(d, torch.zeros(1, 2, 4, 4), d, d, n, d > 0)


# ------------------------------------------------------------------------------------------- surfaces
def _grid(nx: int, ny: int, spacing: float = 1.0, z: float = 0.0) -> np.ndarray:
    x, y = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], -1)


def test_point_sets_offset_by_d_have_chamfer_d():
    truth = _grid(10, 10)
    d = 0.3
    m = surface_metrics(truth + [0.0, 0.0, d], truth, threshold=0.5)
    assert (m.accuracy, m.completeness, m.chamfer) == pytest.approx((d, d, d), abs=1e-12)
    assert (m.precision, m.recall, m.fscore) == (1.0, 1.0, 1.0)
    tight = surface_metrics(truth + [0.0, 0.0, d], truth, threshold=0.2)
    assert (tight.precision, tight.recall, tight.fscore) == (0.0, 0.0, 0.0)


def test_fscore_accuracy_and_completeness_of_a_half_lifted_grid():
    # Truth: a 10 x 10 grid, spacing 1. Reconstruction: the same points, columns x < 5 lifted by 5.
    # Lifted points are 5 from the truth; truth point in column x < 5 is 5 - x from column 5.
    truth = _grid(10, 10)
    rec = truth.copy()
    lifted = rec[:, 0] < 5
    rec[lifted, 2] = 5.0
    m = surface_metrics(rec, truth, threshold=1.5)
    assert m.accuracy == pytest.approx(2.5)
    assert m.completeness == pytest.approx(1.5)  # mean of (5, 4, 3, 2, 1, 0, 0, 0, 0, 0)
    assert m.chamfer == pytest.approx(2.0)
    assert m.precision == pytest.approx(0.5) and m.recall == pytest.approx(0.6)
    assert m.fscore == pytest.approx(2 * 0.5 * 0.6 / 1.1)
    # Opacity weights: lifted points half present -> accuracy 0.5 * 5 * 50 / (0.5 * 50 + 50).
    w = np.where(lifted, 0.5, 1.0)
    weighted = surface_metrics(rec, truth, threshold=1.5, weights=torch.from_numpy(w))
    assert weighted.accuracy == pytest.approx(125 / 75)
    assert weighted.precision == pytest.approx(50 / 75)
    assert weighted.completeness == pytest.approx(1.5)
    # Absent points (weight 0) are not there: perfect accuracy, completeness from the rest.
    absent = surface_metrics(rec, truth, threshold=1.5, weights=np.where(lifted, 0.0, 1.0))
    assert absent.accuracy == 0.0 and absent.completeness == pytest.approx(1.5)
    assert absent.num_reconstruction == 50
    # An outlier cap of 4.5 drops the lifted distances (5) and the truth's 5 from the means.
    capped = surface_metrics(rec, truth, threshold=1.5, max_distance=4.5)
    assert capped.accuracy == 0.0 and capped.completeness == pytest.approx(10 * 10 / 90)


def test_empty_reconstruction_completes_nothing():
    m = surface_metrics(np.zeros((3, 3)), _grid(2, 2), threshold=1.0, weights=np.zeros(3))
    assert math.isnan(m.accuracy) and m.fscore == 0.0 and m.recall == 0.0
    with pytest.raises(SurfSplatInputError, match="weights"):
        surface_metrics(np.zeros((3, 3)), _grid(2, 2), threshold=1.0, weights=-np.ones(3))
    with pytest.raises(SurfSplatInputError, match="reconstruction: expected points"):
        surface_metrics(np.zeros((3, 2)), _grid(2, 2), threshold=1.0)


def test_mesh_samples_are_uniform_by_area_on_the_triangles():
    # A 2 x 1 rectangle cut into a large and a small triangle: samples spread uniformly over it.
    vertices = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    p = sample_mesh(vertices, faces, 40_000, seed=1)
    assert np.abs(p[:, 2]).max() == 0.0 and p[:, 0].min() >= 0 and p[:, 0].max() <= 2 and p[:, 1].max() <= 1
    # Uniform on [0, 2] x [0, 1]: mean (1, 0.5), standard errors 0.577 / 200 and 0.289 / 200.
    assert abs(p[:, 0].mean() - 1.0) < 4 * 0.577 / 200 and abs(p[:, 1].mean() - 0.5) < 4 * 0.289 / 200
    below = p[:, 1] < p[:, 0] / 2  # the first triangle, half the area
    assert abs(below.mean() - 0.5) < 4 * 0.5 / 200
    # Points drawn on a surface are at distance 0 from a dense truth grid's plane, up to the grid spacing.
    m = surface_metrics(p[:2000], _grid(201, 101, spacing=0.01), threshold=0.01)
    assert m.accuracy < 0.0071 and m.precision == 1.0


# ------------------------------------------------------------------------------------------- DTU
def _write_ply(path, points: np.ndarray) -> None:
    vertex = np.empty(points.shape[0], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))


def _dtu_folder(tmp_path, scan: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic object in DTU's layout: reference points on the plane z = 0 over [0, 20) x [0, 20)
    (spacing 0.5 mm) plus a 'table' at z = -10 that the plane z > -5 cuts away; observed cells only
    where round(x) < 10 (Res 1 mm, BB from (0, 0, -40) to (20, 20, 40))."""
    top = _grid(40, 40, spacing=0.5)
    table = _grid(40, 40, spacing=0.5, z=-10.0)
    (tmp_path / "ObsMask").mkdir()
    (tmp_path / "Points" / "stl").mkdir(parents=True)
    _write_ply(tmp_path / "Points" / "stl" / f"stl{scan:03}_total.ply", np.concatenate([top, table]))
    mask = np.zeros((21, 21, 81), dtype=np.uint8)
    mask[:10] = 1
    savemat(
        tmp_path / "ObsMask" / f"ObsMask{scan}_10.mat",
        {"ObsMask": mask, "BB": np.array([[0.0, 0.0, -40.0], [20.0, 20.0, 40.0]]), "Res": np.array([[1.0]])},
    )
    savemat(tmp_path / "ObsMask" / f"Plane{scan}.mat", {"P": np.array([[0.0], [0.0], [1.0], [5.0]])})
    return top, table


def test_dtu_protocol_on_a_synthetic_object_in_dtus_layout(tmp_path):
    top, _ = _dtu_folder(tmp_path)
    reference = load_dtu_reference(tmp_path, 7)
    assert reference.points.shape == (3200, 3) and reference.obs_mask.shape == (21, 21, 81)
    d = 0.25
    rec = top + [0.0, 0.0, d]
    # Exact duplicates are thinned by the 0.2 mm down-sampling: they change no number.
    rec = np.concatenate([rec, rec])
    # Outliers over observed cells: 10 mm off (kept: below the 20 mm cap) and 25 mm off (over the cap);
    # one 8 mm off over an unobserved cell (x >= 10; left out of accuracy).
    near_outliers = np.array([[2.0, 2.0, 10.0], [3.0, 3.0, 10.0]])
    far_outlier = np.array([[2.0, 2.0, -35.0]])  # 25 mm below the table (accuracy uses every STL point)
    unobserved = np.array([[15.0, 15.0, 8.0]])
    m = dtu_chamfer(np.concatenate([rec, near_outliers, far_outlier, unobserved]), reference)
    assert m.num_points == 1600 + 4
    # Observed: round(x) < 10, i.e. the 19 columns x = 0 ... 9.0 (9.5 rounds half to even, to 10).
    observed = 19 * 40
    assert m.num_observed == observed + 3
    assert m.accuracy == pytest.approx((observed * d + 2 * 10.0) / (observed + 2), abs=1e-5)
    # Completeness: only the top (the table is below the plane); each point has a reconstruction d above it.
    assert m.num_reference == 1600
    assert m.completeness == pytest.approx(d, abs=1e-6)
    assert m.overall == pytest.approx((m.accuracy + m.completeness) / 2)


def test_dtu_completeness_without_the_plane_cut_would_count_the_table(tmp_path):
    top, table = _dtu_folder(tmp_path)
    reference = load_dtu_reference(tmp_path, 7)
    lowered = reference.__class__(
        points=reference.points,
        obs_mask=reference.obs_mask,
        bounds=reference.bounds,
        resolution=reference.resolution,
        plane=np.array([0.0, 0.0, 1.0, 20.0]),  # everything above z = -20: the table counts, 10 mm away
    )
    m = dtu_chamfer(top, lowered)
    assert m.num_reference == 3200 and m.completeness == pytest.approx(5.0, abs=1e-6)


def test_dtu_downsampling_keeps_one_point_per_cluster():
    grid = _grid(10, 10, spacing=1.0)
    cloud = np.concatenate([grid + offset for offset in ([0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.15])])
    kept = downsample(cloud, 0.2, seed=3)
    assert kept.shape == (100, 3)
    assert np.abs(kept - np.round(kept)).max() <= 0.15 + 1e-12


def test_dtu_mesh_sampling_density_and_mesh_path(tmp_path):
    # A 10 x 10 mm square of two triangles sampled at 0.2 mm: about one point per 0.04 mm^2 (+ vertices).
    vertices = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 10.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    pts = sample_mesh_dtu(vertices, faces, 0.2)
    assert abs(pts.shape[0] - 100 / 0.04) < 0.05 * 2500
    assert np.abs(pts[:, 2]).max() == 0.0
    top, _ = _dtu_folder(tmp_path)
    reference = load_dtu_reference(tmp_path, 7)
    mesh = dtu_chamfer_mesh(
        torch.tensor([[0.0, 0.0, 0.5], [19.5, 0.0, 0.5], [19.5, 19.5, 0.5], [0.0, 19.5, 0.5]]),
        torch.tensor([[0, 1, 2], [0, 2, 3]]),
        reference,
    )
    # A flat mesh 0.5 mm above the reference plane: every nearest distance is at least 0.5 and at most
    # sqrt(0.5^2 + 0.25^2 + 0.25^2) (half the 0.5 mm reference spacing in x and y).
    assert 0.5 - 1e-6 <= mesh.accuracy <= math.sqrt(0.375) + 1e-6
    assert mesh.completeness == pytest.approx(0.5, abs=0.02)


def test_dtu_reference_errors_name_the_file_and_field(tmp_path):
    with pytest.raises(FileNotFoundError, match="ObsMask7_10.mat"):
        load_dtu_reference(tmp_path, 7)
    _dtu_folder(tmp_path)
    savemat(tmp_path / "ObsMask" / "Plane7.mat", {"Q": np.zeros(4)})
    with pytest.raises(SurfSplatInputError, match=r"Plane7.mat: missing field\(s\) \['P'\]"):
        load_dtu_reference(tmp_path, 7)
