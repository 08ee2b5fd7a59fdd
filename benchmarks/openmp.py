"""OpenMP's wait policy: the CPU seconds of one `surfsplat reconstruct` with idle threads sleeping (the
command line's default, `surfsplat._openmp`) against GNU OpenMP's own default, which spins each idle
thread up to 300,000 times after every parallel region.

    python benchmarks/openmp.py                          # fern, 600 fit steps, each policy twice (A B A B)
    python benchmarks/openmp.py --steps 0 --repeats 1    # the shipped step budget, once each

GNU's default is asked for as `OMP_WAIT_POLICY=ACTIVE GOMP_SPINCOUNT=300000` (the spin count libgomp
takes when neither is set; the command line would otherwise set PASSIVE). The runs alternate, so a drift
of the machine's speed reaches both; the held-out PSNR shows they compute the same scene. Writes
benchmarks/results/openmp.json and prints a table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
from pathlib import Path

from common import machine, reconstruct_cli, sample_data, text_table, write_results

POLICIES = {
    "sleep (PASSIVE, the command line's)": {"OMP_WAIT_POLICY": "PASSIVE"},
    "spin (GNU's default)": {"OMP_WAIT_POLICY": "ACTIVE", "GOMP_SPINCOUNT": "300000"},
}


def one_run(images: list[str], folder: Path, steps: int, env: dict[str, str]) -> dict:
    saved = {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    os.environ.update(env)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            flags = ["--images-folder", "images_8", "--holdout-every", "8", "--formats", "ply", "--raw-3dgs"]
            if steps:
                flags += ["--optimize-steps", str(steps)]
            return reconstruct_cli(images, folder, Path(tmp) / "out", flags)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="folder holding llff_fern")
    parser.add_argument("--steps", type=int, default=600, help="fit steps (0: the shipped budget)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    from surfsplat.data.images import list_images

    folder = sample_data(args.data) / "llff_fern"
    images = [str(p) for p in list_images(folder / "images_8")]
    runs: dict[str, list[dict]] = {name: [] for name in POLICIES}
    for _ in range(args.repeats):
        for name, env in POLICIES.items():
            record = one_run(images, folder, args.steps, env)
            runs[name].append({k: record[k] for k in ("cpu_seconds", "wall_seconds", "peak_rss_mb", "held_out_psnr")})
            print(name, runs[name][-1], flush=True)
    rows = []
    for name, records in runs.items():
        cpu = statistics.median(r["cpu_seconds"] for r in records)
        wall = statistics.median(r["wall_seconds"] for r in records)
        rows.append([name, cpu, wall, records[0]["held_out_psnr"]])
    spin = rows[1][1]
    for row in rows:
        row.append(row[1] / spin)
    document = {"machine": machine(), "steps": args.steps or "shipped", "runs": runs, "table": rows}
    path = write_results("openmp", document)
    print(text_table(["policy", "CPU s (median)", "wall s", "held-out PSNR", "CPU / spin"], rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
