"""Geometry of reconstructions against exact truth: what `surfsplat eval --geometry` adds.

    evaluator = GeometryEvaluator(GeometryConfig())
    for sample in samples:                                     # evaluate.EvalSample
        prediction = predict_sample(model, sample, (1,))
        evaluator.add(sample, prediction)                      # None where the scene has no truth
    print(format_geometry_table({"model": evaluator.report()}))

Truth exists for procedural scenes only: chunks written by `write_synthetic_chunks` (keys
`synthetic-{seed}-{i}`) are the rooms `scene_from_key` rebuilds, and each is first checked against
the depth stored in its chunk (a chunk written with another SyntheticConfig would disagree, and is
refused rather than scored against the wrong room). Other scenes (RealEstate10K, DTU images, ...)
have no dense truth: they are counted and named, never given numbers.

Per scene, with the context views' cameras C and the target views' cameras T (x1 resolution):
- target views: the rendered depth and normals against the ray-cast truth, over pixels whose true
  surface point some context view sees (`geometry_truth(..., seen_from=C)`) and where the render's
  alpha >= min_alpha (coverage = the share of such pixels that are). A render without forced alpha
  blending is divided by alpha first, so every variant is scored on the weighted mean it composites.
- surfaces: truth = area-uniform samples of the surfaces the context views see; reconstruction =
  the surfel centres weighted by opacity, and points sampled uniformly by area on the TSDF mesh
  fused from the reconstruction's depth rendered at C and T (the mesh `surfsplat export` writes),
  rendered at `mesh_scale` times the input resolution: a projective TSDF with a nearest-pixel
  lookup is only as fine as its depth maps (an exact reconstruction of a procedural room meshes
  ~10 cm off from 64-pixel depth maps, ~4 cm from 128-pixel ones), and surfels render at any scale.
  Accuracy, completeness, Chamfer and F-score at `threshold` metres (`metrics.geometry`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from ..data.synthetic.scene import SyntheticScene
from ..data.synthetic.truth import Viewpoints, geometry_truth, scene_from_key, surface_samples
from ..export.mesh import TsdfConfig, extract_mesh, tsdf_fusion
from ..geometry.cameras import Cameras
from ..metrics.geometry import normalize_by_alpha, sample_mesh, surface_metrics, view_geometry
from ..render import RenderOutput, render
from ..utils.checks import SurfSplatInputError

VIEW_COLUMNS = (
    "abs_rel",
    "rmse",
    "delta1",
    "mean_deg",
    "median_deg",
    "within_11_25",
    "within_22_5",
    "within_30",
    "coverage",
)
SURFACE_COLUMNS = ("accuracy", "completeness", "chamfer", "precision", "recall", "fscore")
COLUMNS = (
    *VIEW_COLUMNS,
    *(f"surfels_{c}" for c in SURFACE_COLUMNS),
    *(f"mesh_{c}" for c in SURFACE_COLUMNS),
    "mesh_faces",
)
EMPTY_MESH_ERRORS = ("volume: no observed zero crossing", "depths: no valid depth sample")  # export.mesh's words
STORED_DEPTH_TOLERANCE = 0.005  # m: chunks keep depth in whole millimetres; a different room is off by far more
NO_TRUTH = (
    "no ground-truth geometry for these scenes: dense truth exists only for procedural scenes "
    "(chunks written by write_synthetic_chunks, keys synthetic-SEED-I, e.g. the data `surfsplat demo` writes)"
)


@dataclass(frozen=True)
class GeometryConfig:
    """How geometry is scored (lengths in the scene's units: metres for procedural rooms)."""

    min_alpha: float = 0.1  # a rendered pixel counts where alpha >= this (the paper's training tau_alpha)
    threshold: float = 0.05  # F-score distance (5 cm, about a pixel's footprint at 3 m in a 64 px view)
    truth_samples: int = 20_000  # true surface points per scene (seen by the context views)
    mesh: bool = True  # also score the TSDF mesh of the reconstruction
    mesh_resolution: int = 64  # TSDF voxels along the longest side
    mesh_scale: int = 2  # depth maps fused into the mesh are rendered at this multiple of the input size
    mesh_samples: int = 20_000  # points sampled on the mesh
    seed: int = 0  # surface and mesh sampling

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_alpha <= 1.0:
            raise SurfSplatInputError(f"geometry min_alpha: expected a value in [0, 1], got {self.min_alpha}")
        if not self.threshold > 0:
            raise SurfSplatInputError(f"geometry threshold: expected a positive distance, got {self.threshold}")
        if self.truth_samples < 1 or self.mesh_samples < 1 or self.mesh_resolution < 8 or self.mesh_scale < 1:
            raise SurfSplatInputError(
                "geometry: truth_samples, mesh_samples, mesh_scale >= 1 and mesh_resolution >= 8 expected"
            )


def procedural_scene(sample) -> tuple[SyntheticScene | None, str | None]:
    """(the procedural room behind an EvalSample, None) or (None, why it has no truth)."""
    scene = scene_from_key(sample.scene)
    if scene is None:
        return None, f"{sample.scene}: not a procedural scene"
    if sample.context_depths is None:
        return None, f"{sample.scene}: the chunk stores no depth to confirm it is procedural room {sample.scene}"
    h, w = sample.context_images.shape[-2:]
    truth = geometry_truth(scene, sample.context_cameras, w, h)
    stored = sample.context_depths.to(torch.float64)
    both = truth.hit & (stored > 0)
    error = float((truth.depth - stored).abs()[both].median()) if bool(both.any()) else math.inf
    if not error <= STORED_DEPTH_TOLERANCE:
        raise SurfSplatInputError(
            f"{sample.scene}: the chunk's depth differs from procedural room {sample.scene} (median "
            f"{error:.3g} m): it was written with another SyntheticConfig, and would be scored against the wrong room"
        )
    return scene, None


def score_scene(
    scene: SyntheticScene,
    gaussians,
    targets: RenderOutput,
    target_cameras: Cameras,
    context_cameras: Cameras,
    width: int,
    height: int,
    config: GeometryConfig = GeometryConfig(),
    normalized: bool = True,
    mesh_views: tuple[RenderOutput, Cameras] | None = None,
) -> dict[str, float]:
    """Every geometry column for one reconstruction of `scene` (see the module doc).

    gaussians: the unbatched surfsplat.Gaussians; targets: their render at target_cameras (x1);
    normalized: whether the renders were divided by alpha (forced alpha blending); mesh_views: their
    renders to fuse into the mesh and those renders' cameras (K for the renders' size), needed when
    config.mesh is set (`GeometryEvaluator` renders C and T at config.mesh_scale).
    """
    seen = Viewpoints(context_cameras.to(dtype=torch.float64), width, height)
    truth = geometry_truth(scene, target_cameras.to(dtype=torch.float64), width, height, seen_from=seen)
    depth, normal = targets.depth.double().cpu(), targets.normal.double().cpu()
    alpha = targets.alpha.double().cpu()
    if not normalized:
        depth = normalize_by_alpha(depth, alpha, config.min_alpha)
        normal = normalize_by_alpha(normal, alpha, config.min_alpha)
    views = view_geometry(depth, normal, alpha, truth.depth, truth.normal, truth.mask, config.min_alpha)
    row: dict[str, float] = {}
    if bool((views.depth.num_valid > 0).any()):
        row.update(views.mean())
    else:
        row.update({c: math.nan for c in VIEW_COLUMNS})
        row["coverage"] = 0.0
    generator = torch.Generator().manual_seed(config.seed)
    true_points = surface_samples(scene, config.truth_samples, seen_from=seen, generator=generator).points
    surfels = surface_metrics(
        gaussians.means.detach().cpu(), true_points, config.threshold, weights=gaussians.opacities.detach().cpu()
    )
    row.update({f"surfels_{c}": getattr(surfels, c) for c in SURFACE_COLUMNS})
    if config.mesh:
        if mesh_views is None:
            raise SurfSplatInputError("mesh_views: the mesh needs the reconstruction's renders and their cameras")
        row.update(_mesh_columns(*mesh_views, true_points, config, normalized))
    return row


def _mesh_columns(renders: RenderOutput, cameras: Cameras, true_points, config, normalized) -> dict:
    depth, alpha = renders.depth.float().cpu(), renders.alpha.float().cpu()
    if not normalized:
        depth = normalize_by_alpha(depth, alpha, config.min_alpha)
    cams = cameras.to(device="cpu", dtype=torch.float32)
    # No mesh (nothing opaque, or no zero crossing): it completes nothing; mesh_faces = 0 says why.
    empty = {f"mesh_{c}": math.nan for c in SURFACE_COLUMNS}
    empty |= {"mesh_precision": 0.0, "mesh_recall": 0.0, "mesh_fscore": 0.0, "mesh_faces": 0.0}
    if not bool((alpha >= config.min_alpha).any()):
        return empty
    try:
        valid = alpha >= config.min_alpha
        volume = tsdf_fusion(depth, cams, valid=valid, config=TsdfConfig(resolution=config.mesh_resolution))
        mesh = extract_mesh(volume)
    except SurfSplatInputError as err:
        # The fused depth has no observed zero crossing (e.g. an untrained network's scattered depth):
        # there is no surface to score, which the row records as an empty mesh. Anything else is an error.
        if not str(err).startswith(EMPTY_MESH_ERRORS):
            raise
        return empty
    points = sample_mesh(mesh.vertices, mesh.faces, config.mesh_samples, seed=config.seed)
    metrics = surface_metrics(points, true_points, config.threshold)
    return {f"mesh_{c}": getattr(metrics, c) for c in SURFACE_COLUMNS} | {"mesh_faces": float(mesh.faces.shape[0])}


@dataclass
class GeometryReport:
    """Geometry columns per scene and their means; which scenes had no truth, and why."""

    config: GeometryConfig
    per_scene: dict[str, dict[str, float]] = field(default_factory=dict)
    without_truth: list[str] = field(default_factory=list)  # one reason per scene left out

    def mean(self) -> dict[str, float] | None:
        """Mean of each column over the scenes where it is defined (None when no scene had truth)."""
        if not self.per_scene:
            return None
        out = {}
        for column in COLUMNS:
            values = [r[column] for r in self.per_scene.values() if column in r and math.isfinite(r[column])]
            out[column] = sum(values) / len(values) if values else math.nan
        return out

    def to_json(self) -> dict:
        return {
            "unavailable": None if self.per_scene else NO_TRUTH,
            "settings": {
                "min_alpha": self.config.min_alpha,
                "threshold": self.config.threshold,
                "truth_samples": self.config.truth_samples,
                "mesh": self.config.mesh,
                "mesh_resolution": self.config.mesh_resolution,
                "mesh_scale": self.config.mesh_scale,
            },
            "mean": self.mean(),
            "per_scene": self.per_scene,
            "num_scenes": len(self.per_scene),
            "without_truth": self.without_truth,
        }


class GeometryEvaluator:
    """Scores each evaluated entry's geometry where its scene has truth (see the module doc)."""

    def __init__(self, config: GeometryConfig = GeometryConfig()) -> None:
        self.config = config
        self._report = GeometryReport(config)

    @torch.no_grad()
    def add(self, sample, prediction) -> dict[str, float] | None:
        """Score one entry (evaluate.EvalSample, evaluate.ScenePrediction with a factor-1 render)."""
        if 1 not in prediction.renders:
            raise SurfSplatInputError("geometry: the prediction needs its factor-1 render (add 1 to --factors)")
        scene, reason = procedural_scene(sample)
        if scene is None:
            self._report.without_truth.append(reason)
            return None
        h, w = sample.target_images.shape[-2:]
        mesh_views = None
        if self.config.mesh:
            s = self.config.mesh_scale
            both = Cameras(
                torch.cat([sample.context_cameras.c2w, sample.target_cameras.c2w]),
                torch.cat([sample.context_cameras.K, sample.target_cameras.K]),
                validate=False,
            ).scaled(float(s))
            cams = both.to(device=prediction.gaussians.means.device, dtype=torch.float32)
            renders = render(
                prediction.gaussians,
                cams,
                w * s,
                h * s,
                mode=prediction.render_mode,
                alpha_threshold=prediction.alpha_threshold,
            )
            mesh_views = (renders, both)
        row = score_scene(
            scene,
            prediction.gaussians,
            prediction.renders[1],
            sample.target_cameras,
            sample.context_cameras,
            w,
            h,
            self.config,
            normalized=prediction.alpha_threshold is not None,
            mesh_views=mesh_views,
        )
        self._report.per_scene[sample.key] = row
        return row

    def report(self) -> GeometryReport:
        return self._report


def _cell(value: float, digits: int) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


# column -> (header, digits)
_TABLE = {
    "abs_rel": ("AbsRel↓", 3),
    "rmse": ("RMSE↓", 3),
    "delta1": ("δ<1.25↑", 3),
    "mean_deg": ("mean°↓", 1),
    "median_deg": ("median°↓", 1),
    "within_11_25": ("<11.25°↑", 3),
    "within_22_5": ("<22.5°↑", 3),
    "within_30": ("<30°↑", 3),
    "coverage": ("cover↑", 3),
    "surfels_accuracy": ("Acc↓", 3),
    "surfels_completeness": ("Comp↓", 3),
    "surfels_chamfer": ("CD↓", 3),
    "surfels_fscore": ("F↑", 3),
    "mesh_accuracy": ("Acc↓", 3),
    "mesh_completeness": ("Comp↓", 3),
    "mesh_chamfer": ("CD↓", 3),
    "mesh_fscore": ("F↑", 3),
}


def format_geometry_table(reports: Mapping[str, GeometryReport]) -> str:
    """Means per method in the paper's layout (column groups over metric columns), or a plain
    statement that no scene had truth. Depth in metres, angles in degrees, distances in metres."""
    if not reports:
        raise SurfSplatInputError("reports: expected at least one method's geometry report")
    first = next(iter(reports.values()))
    if all(not r.per_scene for r in reports.values()):
        return f"Geometry: {NO_TRUTH}; {len(first.without_truth)} scene(s) left out, no geometry numbers."
    threshold = first.config.threshold
    groups = [
        ("Depth (target views)", ("abs_rel", "rmse", "delta1")),
        ("Normals (target views)", ("mean_deg", "median_deg", "within_11_25", "within_22_5", "within_30")),
        ("", ("coverage",)),
        (
            "Surfels (opacity-weighted)",
            ("surfels_accuracy", "surfels_completeness", "surfels_chamfer", "surfels_fscore"),
        ),
    ]
    if first.config.mesh:
        groups.append(("TSDF mesh", ("mesh_accuracy", "mesh_completeness", "mesh_chamfer", "mesh_fscore")))
    rows = {name: r.mean() for name, r in reports.items()}
    name_w = max(len("Method"), *(len(n) for n in reports))
    cells = {
        name: {c: _cell(row[c], _TABLE[c][1]) if row else "n/a" for _, cols in groups for c in cols}
        for name, row in rows.items()
    }
    width = {c: max(len(_TABLE[c][0]), *(len(cells[n][c]) for n in cells)) for _, cols in groups for c in cols}
    group_w = [max(len(title), sum(width[c] for c in cols) + len(cols) - 1) for title, cols in groups]

    def line(values: list[str]) -> str:
        return " | ".join(v.rjust(w) for v, w in zip(values, group_w))

    def group_cells(pick) -> list[str]:
        return [" ".join(pick(c).rjust(width[c]) for c in cols) for _, cols in groups]

    lines = [
        " " * name_w + " | " + " | ".join(title.center(w) for (title, _), w in zip(groups, group_w)),
        "Method".ljust(name_w) + " | " + line(group_cells(lambda c: _TABLE[c][0])),
        "-" * name_w + "-+-" + "-+-".join("-" * w for w in group_w),
    ]
    for name in reports:
        lines.append(name.ljust(name_w) + " | " + line(group_cells(lambda c, n=name: cells[n][c])))
    counts = ", ".join(f"{len(r.per_scene)}" for r in reports.values())
    lines.append(
        f"Geometry against exact truth: scenes per method {counts}; target views at x1, pixels and surfaces "
        f"seen by the context views; alpha >= {first.config.min_alpha}; metres and degrees; F-score at "
        f"{threshold * 100:g} cm; CD = (Acc + Comp) / 2"
        + (f"; mesh fused from x{first.config.mesh_scale} depth renders." if first.config.mesh else ".")
    )
    left_out = len(first.without_truth)
    if left_out:
        lines.append(f"{left_out} scene(s) without ground-truth geometry left out (e.g. {first.without_truth[0]}).")
    return "\n".join(line.rstrip() for line in lines)


__all__ = [
    "COLUMNS",
    "GeometryConfig",
    "GeometryEvaluator",
    "GeometryReport",
    "format_geometry_table",
    "procedural_scene",
    "score_scene",
]
