"""Evaluation: a model scored over an evaluation index, the paper's tables, and geometry against
exact truth. The per-quantity math (PSNR, SSIM, LPIPS, HRRC, depth, closure, surface distances)
lives in `surfsplat.metrics`; this package runs it over datasets and writes the results.

    model, name = load_model(ModelSpec("tiny-synthetic"))      # surfsplat.model.loading
    result = evaluate(model, iter_index_samples(roots, index), EvalConfig(), name=name)
    print(format_results({name: result}))

- `run`: the index's samples, the forward pass, `evaluate`, tables and files.
- `geometry`: depth, normals and surfaces of reconstructions against procedural rooms' truth.
"""

from .geometry import (
    GeometryConfig,
    GeometryEvaluator,
    GeometryReport,
    format_geometry_table,
    procedural_scene,
    score_scene,
)
from .run import (
    RESULT_FILES,
    EvalConfig,
    EvalSample,
    EvaluationResult,
    SampleCounts,
    ScenePrediction,
    evaluate,
    format_results,
    geometry_csv,
    iter_index_samples,
    peak_memory,
    peak_rss_bytes,
    per_scene_csv,
    predict_sample,
    write_results,
)

__all__ = [
    "RESULT_FILES",
    "EvalConfig",
    "EvalSample",
    "EvaluationResult",
    "GeometryConfig",
    "GeometryEvaluator",
    "GeometryReport",
    "SampleCounts",
    "ScenePrediction",
    "evaluate",
    "format_geometry_table",
    "format_results",
    "geometry_csv",
    "iter_index_samples",
    "peak_memory",
    "peak_rss_bytes",
    "per_scene_csv",
    "predict_sample",
    "procedural_scene",
    "score_scene",
    "write_results",
]
