"""Geometry metrics: rendered depth and normals at target views, and surfaces as point sets.

Per view (plain tensors in, one value per image out):
- depth: `surfsplat.metrics.depth.depth_metrics` (AbsRel, RMSE, delta < 1.25, ...) over a mask;
- normals: angle between predicted and true unit normals, theta = atan2(|a x b|, a . b) (accurate
  near 0 and 180 deg, where acos is not); per image the mean and median angle and the share of
  pixels under 11.25, 22.5 and 30 deg (the thresholds of Fouhey et al. 2013 and every normal
  benchmark since). A predicted normal of zero length inside the mask is an answer of nothing: it
  counts as 180 deg.
- `view_geometry` puts both together over the pixels whose true surface the reconstruction could see
  (the caller's truth mask) and where the render is opaque enough (alpha >= min_alpha), and reports
  that share as coverage.

Between point sets (reconstruction R, truth T; d(x, S) = distance from x to its nearest point of S):
- accuracy     = sum_i w_i d(r_i, T) / sum_i w_i          (reconstruction -> truth, weighted)
- completeness = mean_j d(t_j, R+)                         (truth -> reconstruction)
- Chamfer      = (accuracy + completeness) / 2             (DTU's "overall")
- precision    = sum_i w_i [d(r_i, T) < tau] / sum_i w_i,  recall = mean_j [d(t_j, R+) < tau]
- F-score      = 2 P R / (P + R) at the distance threshold tau (Knapitsch et al. 2017)
Weights w (e.g. surfel opacities) say how much each reconstructed point is there: a faint point far
from every surface costs little accuracy. Completeness asks whether any reconstructed point lies
near each true point, so it is taken over R+ = the points with w > 0, unweighted. Without weights
every point counts 1. `max_distance` (DTU: 20 mm) drops distances at or above it from the two means
(not from precision or recall), as DTU's evaluation does with outliers.

Nearest neighbours: scipy's cKDTree (exact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor
from .depth import DepthMetrics, depth_metrics

NORMAL_THRESHOLDS_DEG = (11.25, 22.5, 30.0)


# ------------------------------------------------------------------------------------------- normals
def angular_error_deg(prediction: Tensor, target: Tensor) -> Tensor:
    """Angle in degrees between vectors [..., 3] (any length); 180 where the prediction is zero."""
    a, b = prediction.double(), target.double()
    cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    dot = (a * b).sum(-1)
    angle = torch.rad2deg(torch.atan2(cross, dot))
    return torch.where(a.norm(dim=-1) > 0, angle, torch.full_like(angle, 180.0))


@dataclass(frozen=True)
class NormalMetrics:
    """Per-image normal errors, each [B]; images without valid pixels hold NaN."""

    mean_deg: Tensor
    median_deg: Tensor
    within_11_25: Tensor  # share of pixels with error < 11.25 deg
    within_22_5: Tensor
    within_30: Tensor
    num_valid: Tensor  # [B] int64

    def mean(self) -> dict[str, float]:
        """Mean over the images that have valid pixels, plus how many did."""
        keep = self.num_valid > 0
        if not bool(keep.any()):
            raise SurfSplatInputError("normal metrics: no image has a valid ground-truth pixel")
        out = {
            f.name: float(getattr(self, f.name)[keep].double().mean()) for f in fields(self) if f.name != "num_valid"
        }
        out["num_images"] = int(keep.sum())
        return out


def normal_metrics(prediction: Tensor, target: Tensor, mask: Tensor | None = None) -> NormalMetrics:
    """Angular errors per image. prediction, target: [B, 3, H, W] normals; mask: bool [B, 1, H, W] or [B, H, W].

    Pixels count where the mask holds and the target has non-zero length.
    """
    check_tensor("prediction", prediction, ("B", 3, "H", "W"))
    check_tensor("target", target, tuple(prediction.shape))
    b, _, h, w = prediction.shape
    valid = target.norm(dim=1) > 0
    if mask is not None:
        valid = valid & _bool_mask(mask, (b, h, w))
    error = angular_error_deg(prediction.movedim(1, -1), target.movedim(1, -1))  # [B, H, W]
    rows: dict[str, list[float]] = {f.name: [] for f in fields(NormalMetrics) if f.name != "num_valid"}
    for k in range(b):
        e = error[k][valid[k]]
        if e.numel() == 0:
            for values in rows.values():
                values.append(math.nan)
            continue
        rows["mean_deg"].append(float(e.mean()))
        # The lower median (torch.median): an observed error, not an average of two.
        rows["median_deg"].append(float(e.median()))
        for name, limit in zip(("within_11_25", "within_22_5", "within_30"), NORMAL_THRESHOLDS_DEG):
            rows[name].append(float((e < limit).double().mean()))
    return NormalMetrics(
        **{name: torch.tensor(values, dtype=torch.float64) for name, values in rows.items()},
        num_valid=valid.sum(dim=(1, 2)).long(),
    )


def _bool_mask(mask: Tensor, shape: tuple[int, int, int]) -> Tensor:
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise SurfSplatInputError(f"mask: expected a bool tensor, got {getattr(mask, 'dtype', type(mask).__name__)}")
    if mask.ndim == 4 and mask.shape[1] == 1:
        mask = mask[:, 0]
    if tuple(mask.shape) != shape:
        raise SurfSplatInputError(
            f"mask: expected shape {shape} (or with a channel axis of 1), got {tuple(mask.shape)}"
        )
    return mask


# ------------------------------------------------------------------------------------------- views
@dataclass(frozen=True)
class ViewGeometry:
    """Depth and normal errors of C rendered views over the scored pixels, and how many were scored."""

    depth: DepthMetrics
    normal: NormalMetrics
    coverage: Tensor  # [C] share of the truth mask's pixels that were scored (render alpha >= min_alpha)

    def mean(self) -> dict[str, float]:
        """abs_rel, rmse, delta1 (depth), mean/median angle and shares (normals), coverage: means over views."""
        depth = self.depth.mean()
        normal = self.normal.mean()
        keep = torch.isfinite(self.coverage)
        return {
            "abs_rel": depth["abs_rel"],
            "rmse": depth["rmse"],
            "delta1": depth["delta1"],
            **{k: v for k, v in normal.items() if k != "num_images"},
            "coverage": float(self.coverage[keep].mean()) if bool(keep.any()) else math.nan,
        }


def view_geometry(
    depth: Tensor,
    normal: Tensor,
    alpha: Tensor,
    true_depth: Tensor,
    true_normal: Tensor,
    true_mask: Tensor,
    min_alpha: float = 0.1,
) -> ViewGeometry:
    """Rendered depth [C, 1, H, W], normals [C, 3, H, W] and alpha [C, 1, H, W] against the truth.

    true_mask: bool [C, 1, H, W], the pixels whose true surface may be scored (e.g. seen by a context
    view). Scored: true_mask & alpha >= min_alpha; coverage = scored / true_mask per view (NaN where
    the truth mask is empty). Depth and normals are taken as given: a renderer without forced alpha
    blending must divide them by alpha first (see `normalize_by_alpha`).
    """
    check_tensor("depth", depth, ("C", 1, "H", "W"))
    c, _, h, w = depth.shape
    check_tensor("normal", normal, (c, 3, h, w))
    check_tensor("alpha", alpha, (c, 1, h, w))
    check_tensor("true_depth", true_depth, (c, 1, h, w))
    check_tensor("true_normal", true_normal, (c, 3, h, w))
    truth = _bool_mask(true_mask, (c, h, w))
    if not 0.0 <= min_alpha <= 1.0:
        raise SurfSplatInputError(f"min_alpha: expected a value in [0, 1], got {min_alpha}")
    scored = truth & (alpha[:, 0] >= min_alpha)
    possible = truth.sum(dim=(1, 2)).double()
    coverage = torch.where(possible > 0, scored.sum(dim=(1, 2)).double() / possible.clamp(min=1), math.nan)
    return ViewGeometry(
        depth=depth_metrics(depth, true_depth, scored),
        normal=normal_metrics(normal, true_normal, scored),
        coverage=coverage,
    )


def normalize_by_alpha(values: Tensor, alpha: Tensor, min_alpha: float) -> Tensor:
    """values [C, K, H, W] / alpha [C, 1, H, W] where alpha >= min_alpha (0 elsewhere): the
    compositing-weighted mean, i.e. what forced alpha blending renders."""
    return torch.where(alpha >= min_alpha, values / alpha.clamp(min=min_alpha), torch.zeros_like(values))


# ------------------------------------------------------------------------------------------- surfaces
@dataclass(frozen=True)
class SurfaceMetrics:
    """Distances between a reconstruction and the true surface (units of the points)."""

    accuracy: float
    completeness: float
    chamfer: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    num_reconstruction: int
    num_truth: int

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def nearest_distances(queries: Tensor | np.ndarray, points: Tensor | np.ndarray) -> np.ndarray:
    """Distance [Q] from each query point [Q, 3] to its nearest point of `points` [P, 3] (float64)."""
    q, p = _points("queries", queries), _points("points", points)
    if p.shape[0] == 0:
        raise SurfSplatInputError("points: the set to search is empty")
    # An unbalanced, non-compacted tree builds ~20x faster and queries as fast (scipy's advice for
    # one-off searches).
    distances, _ = cKDTree(p, balanced_tree=False, compact_nodes=False).query(q, k=1)
    return np.asarray(distances, dtype=np.float64)


def surface_metrics(
    reconstruction: Tensor | np.ndarray,
    truth: Tensor | np.ndarray,
    threshold: float,
    weights: Tensor | np.ndarray | None = None,
    max_distance: float | None = None,
) -> SurfaceMetrics:
    """Accuracy, completeness, Chamfer, precision, recall, F-score of points [N, 3] against [M, 3].

    weights: [N] non-negative (e.g. opacities), see the module doc. An empty reconstruction (or all
    weights 0) has no accuracy and completes nothing: NaN distances, precision, recall and F-score 0.
    """
    rec, tru = _points("reconstruction", reconstruction), _points("truth", truth)
    if tru.shape[0] == 0:
        raise SurfSplatInputError("truth: expected at least one true surface point")
    if not threshold > 0:
        raise SurfSplatInputError(f"threshold: expected a positive distance, got {threshold}")
    if max_distance is not None and not max_distance > 0:
        raise SurfSplatInputError(f"max_distance: expected a positive distance, got {max_distance}")
    w = np.ones(rec.shape[0]) if weights is None else _weights(weights, rec.shape[0])
    present = w > 0
    if not bool(present.any()):
        return SurfaceMetrics(math.nan, math.nan, math.nan, 0.0, 0.0, 0.0, threshold, 0, tru.shape[0])
    rec, w = rec[present], w[present]
    d_rec = nearest_distances(rec, tru)
    d_tru = nearest_distances(tru, rec)
    kept_rec = d_rec < max_distance if max_distance is not None else np.ones_like(d_rec, dtype=bool)
    kept_tru = d_tru < max_distance if max_distance is not None else np.ones_like(d_tru, dtype=bool)
    accuracy = float((w * d_rec)[kept_rec].sum() / w[kept_rec].sum()) if kept_rec.any() else math.nan
    completeness = float(d_tru[kept_tru].mean()) if kept_tru.any() else math.nan
    precision = float((w * (d_rec < threshold)).sum() / w.sum())
    recall = float((d_tru < threshold).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return SurfaceMetrics(
        accuracy=accuracy,
        completeness=completeness,
        chamfer=(accuracy + completeness) / 2,
        precision=precision,
        recall=recall,
        fscore=fscore,
        threshold=float(threshold),
        num_reconstruction=int(rec.shape[0]),
        num_truth=int(tru.shape[0]),
    )


def sample_mesh(vertices: Tensor | np.ndarray, faces: Tensor | np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """`count` points [count, 3] uniform by area on a triangle mesh (vertices [V, 3], faces [F, 3]).

    A triangle is picked with probability proportional to its area, then a point uniform in it:
    barycentric (1 - sqrt(u), sqrt(u) (1 - v), sqrt(u) v) (Osada et al. 2002).
    """
    v = _points("vertices", vertices)
    f = np.asarray(faces.cpu().numpy() if isinstance(faces, Tensor) else faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise SurfSplatInputError(f"faces: expected integer indices [F, 3], got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise SurfSplatInputError(f"faces: indices must lie in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
    if count < 1:
        raise SurfSplatInputError(f"count: expected at least 1 sample, got {count}")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    if f.shape[0] == 0 or not area.sum() > 0:
        raise SurfSplatInputError("mesh: no triangle with a positive area to sample")
    rng = np.random.default_rng(seed)
    which = rng.choice(f.shape[0], size=count, p=area / area.sum())
    u, w2 = rng.random(count), rng.random(count)
    su = np.sqrt(u)
    return (1 - su)[:, None] * a[which] + (su * (1 - w2))[:, None] * b[which] + (su * w2)[:, None] * c[which]


def _points(name: str, value: Tensor | np.ndarray) -> np.ndarray:
    array = value.detach().cpu().double().numpy() if isinstance(value, Tensor) else np.asarray(value, np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise SurfSplatInputError(f"{name}: expected points of shape [N, 3], got {array.shape}")
    if not np.isfinite(array).all():
        raise SurfSplatInputError(f"{name}: points must be finite")
    return array


def _weights(value: Tensor | np.ndarray, n: int) -> np.ndarray:
    w = value.detach().cpu().double().numpy() if isinstance(value, Tensor) else np.asarray(value, np.float64)
    if w.shape != (n,):
        raise SurfSplatInputError(f"weights: expected shape ({n},), got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise SurfSplatInputError("weights: expected finite non-negative values")
    return w


__all__ = [
    "NORMAL_THRESHOLDS_DEG",
    "NormalMetrics",
    "SurfaceMetrics",
    "ViewGeometry",
    "angular_error_deg",
    "nearest_distances",
    "normal_metrics",
    "normalize_by_alpha",
    "sample_mesh",
    "surface_metrics",
    "view_geometry",
]
