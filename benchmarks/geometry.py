"""Geometry metrics benchmark: 100,000 surfels and a 256x256 view of a procedural room.

Times (median of repeats after a warm-up) each part of a scene's geometry score:
    view metrics       depth AbsRel/RMSE/delta and normal errors + coverage over a 256x256 view
    surface metrics    accuracy / completeness / Chamfer / F-score: 100k opacity-weighted surfel centres
                       against 100k true surface samples (two cKDTree builds and queries)
    mesh sampling      100k area-uniform points on a 200k-triangle mesh
and, separately, the truth they need (analytic ray casting, float64): the 256x256 view's depth,
normals and visibility mask, and 100k surface samples seen by two context views. The reconstruction
is the truth perturbed (2 cm noise on depth and surfel centres, normals turned by a few degrees), so
the neighbour searches do the work a real evaluation does. Writes JSON and prints a table; the
load average is recorded with the times (on a shared machine wall time alone says little).

    python benchmarks/geometry.py
    python benchmarks/geometry.py --surfels 200000 --size 512 --threads 2
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from common import RESULTS, write_results
from surfsplat.data.synthetic import (
    SyntheticDataset,
    SyntheticDatasetConfig,
    Viewpoints,
    geometry_truth,
    surface_samples,
)
from surfsplat.metrics.geometry import sample_mesh, surface_metrics, view_geometry
from surfsplat.train.loop import cpu_threads


def timed(fn: Callable[[], object], repeats: int) -> dict[str, object]:
    """Median and every repeat of wall time and of this process's CPU time (which a crowded machine
    inflates much less than wall time: it counts only the time the process ran)."""
    fn()  # warm-up (imports, allocator)
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return {"median": statistics.median(wall), "all": wall, "cpu_median": statistics.median(cpu), "cpu_all": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surfels", type=int, default=100_000)
    parser.add_argument("--size", type=int, default=256, help="square view size")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (cKDTree queries are single-threaded)")
    parser.add_argument("--out", type=Path, default=RESULTS / "geometry.json")
    args = parser.parse_args()

    with cpu_threads(args.threads):
        rows, counts = run(args.surfels, args.size, args.repeats)
    document = {
        "settings": {
            "surfels": args.surfels,
            "size": args.size,
            "repeats": args.repeats,
            "threads": args.threads,
            "torch": torch.__version__,
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0],
        },
        "counts": counts,
        "seconds": rows,
    }
    write_results(args.out, document)
    width = max(len(k) for k in rows)
    print(f"{'part'.ljust(width)} | wall s (median) | CPU s (median) | wall s, all repeats")
    print("-" * (width + 70))
    for name, row in rows.items():
        print(
            f"{name.ljust(width)} | {row['median']:15.3f} | {row['cpu_median']:14.3f} | "
            + ", ".join(f"{t:.3f}" for t in row["all"])
        )
    wall = rows["view metrics"]["median"] + rows["surface metrics"]["median"]
    cpu = rows["view metrics"]["cpu_median"] + rows["surface metrics"]["cpu_median"]
    print(
        f"metrics of one scene (view + surface): {wall:.3f} s wall, {cpu:.3f} s CPU; "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
    )
    print(f"wrote {args.out}")


def run(num_surfels: int, size: int, repeats: int) -> tuple[dict, dict]:
    dataset = SyntheticDataset(SyntheticDatasetConfig(length=1, seed=3, image_shape=(size, size)))
    scene = dataset.scene(0)
    context, target = dataset.cameras(0)
    target = target[0]
    seen = Viewpoints(context, size, size)
    g = torch.Generator().manual_seed(0)

    rows: dict[str, dict] = {}

    def record(name: str, fn: Callable[[], object], n: int = repeats) -> None:
        rows[name] = timed(fn, n)

    # Truth (computed once per scene in an evaluation; timed with fewer repeats: it is the slow part).
    truth = geometry_truth(scene, target, size, size, seen_from=seen)
    record(
        f"truth: {size}x{size} view (ray cast + visibility)",
        lambda: geometry_truth(scene, target, size, size, seen_from=seen),
        2,
    )
    samples = surface_samples(scene, num_surfels, seen_from=seen, generator=torch.Generator().manual_seed(1)).points
    record(
        "truth: surface samples seen by 2 views",
        lambda: surface_samples(scene, num_surfels, seen_from=seen, generator=torch.Generator().manual_seed(1)),
        2,
    )

    # A plausible reconstruction: truth perturbed.
    depth = (truth.depth + 0.02 * torch.randn(truth.depth.shape, generator=g, dtype=torch.float64)).float()
    normal = torch.nn.functional.normalize(
        truth.normal + 0.05 * torch.randn(truth.normal.shape, generator=g, dtype=torch.float64), dim=1
    ).float()
    alpha = torch.rand(truth.depth.shape, generator=g)
    surfels = samples + 0.02 * torch.randn(samples.shape, generator=g, dtype=torch.float64)
    surfels = surfels[torch.randperm(surfels.shape[0], generator=g)]
    opacities = torch.rand(num_surfels, generator=g)
    true_points = surface_samples(scene, num_surfels, seen_from=seen, generator=torch.Generator().manual_seed(2)).points

    record(
        "view metrics",
        lambda: view_geometry(depth, normal, alpha, truth.depth.float(), truth.normal.float(), truth.mask).mean(),
    )
    record("surface metrics", lambda: surface_metrics(surfels, true_points, 0.05, weights=opacities))

    # A 200k-triangle mesh: a 317 x 317 grid of quads, two triangles each.
    n = 317
    xy = np.stack(np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.concatenate([xy, np.sin(xy[:, :1] / 10)], 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    faces = np.concatenate([np.stack([a, a + n + 1, a + 1], -1), np.stack([a + 1, a + n + 1, a + n + 2], -1)])
    record("mesh sampling (200k triangles)", lambda: sample_mesh(vertices, faces, num_surfels))

    counts = {
        "surfels": num_surfels,
        "truth_samples": int(true_points.shape[0]),
        "view_pixels_scored": int(
            view_geometry(
                depth, normal, alpha, truth.depth.float(), truth.normal.float(), truth.mask
            ).depth.num_valid.sum()
        ),
        "mesh_triangles": int(faces.shape[0]),
    }
    return rows, counts


if __name__ == "__main__":
    main()
