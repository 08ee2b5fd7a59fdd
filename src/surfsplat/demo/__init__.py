"""The demo as a library: the whole product on a fresh machine, nothing downloaded.

    from surfsplat.demo import DemoConfig, run_demo
    result = run_demo(DemoConfig.quick(), Path("outputs/quick"))     # `surfsplat demo --quick`

1. data:     procedural synthetic rooms (exact images and depth at any resolution); held-out
             evaluation scenes are written as chunks with an evaluation index, the same files
             `surfsplat eval` reads;
2. train:    the `tiny` preset (MSE only: lambda_lpips = 0, no VGG files needed) for 150 steps,
             stopped at a hard time limit on a slow or busy machine;
3. evaluate: the shipped model (`tiny-synthetic`, trained on procedural rooms: its metadata says
             how), the model just trained and the untrained network: renders at x1, x2, x4 (K
             scaled) scored against the ground truth upsampled bicubically (the paper's HRRC) and
             against native high-resolution truth, which the synthetic scenes provide exactly;
             geometry (depth and normals at the target views, surfels and TSDF mesh against the
             true surfaces);
4. export:   surfels (PLY), a turntable and a camera-path MP4, a TSDF mesh of one scene (shipped
             model), pictured from a viewpoint no input saw;
5. report:   report.html (tables, image and error-map grids at the three resolutions, the mesh,
             a paragraph reading the numbers, training curve) and metrics.json.

`pipeline` holds the phases, `report` the page. The benchmarks reuse `write_eval_data` and
`native_truth` for the same held-out rooms.
"""

from .pipeline import DemoConfig, DemoResult, Phase, eval_targets, native_truth, run_demo, write_eval_data

__all__ = ["DemoConfig", "DemoResult", "Phase", "eval_targets", "native_truth", "run_demo", "write_eval_data"]
