"""Build `tests/data/distorted/`: DTU views as a camera with a lens would have taken them.

    python tests/data/make_distorted.py [--out tests/data/distorted]

Deterministic (fixed views, fixed seed); it reads only the repository's own DTU fixture
(`tests/data/dtu_scan24`), so it runs in any clone. The five first views of that fixture (100x75,
pinhole, IDR cameras) are resampled to one OPENCV lens (`LENS` below, known coefficients) and written
as the captures the readers meet, by `surfsplat.testing.lens_capture.write_lens_capture` (its module
doc has the layout):
- `images/000000.png` ... the distorted photos (8-bit RGB, bicubic);
- `sparse/0/` a COLMAP model written by pycolmap (binary), `sparse/text/` the same model as text; one
  OPENCV camera, the views' poses, and 3D points (random, inside the object's sphere) observed where
  the lens projects them;
- `transforms.json`: nerfstudio's dialect (camera_model OPENCV, the coefficients at the top level);
- `instant_ngp/transforms.json`: instant-ngp's dialect (no camera_model, fl_x without fl_y, float w/h);
- `truth.json`: the lens, and per view the source photo, its pinhole K (IDR's, skew dropped) and its
  camera-to-world (OpenCV axes), so a reader's undistortion can be checked against the source;
- `fisheye/`: the same views through an OPENCV_FISHEYE lens (`FISHEYE`), with nerfstudio's
  `transforms.json` (camera_model OPENCV_FISHEYE, k1..k4) and its own `truth.json`.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import torch

from surfsplat.data.formats.dtu import load_dtu
from surfsplat.geometry.lens import Lens
from surfsplat.testing.lens_capture import PinholeView, write_lens_capture

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "dtu_scan24"
VIEWS = [0, 1, 2, 3, 4]
WIDTH, HEIGHT = 100, 75
# One lens for every view: the focal length a little longer than DTU's (180.8 px at this size) and the
# principal point near DTU's (51.5, 38.7), so the lens sees nothing beyond the pinhole photos (no blank
# pixel); a barrel distortion of 2-3 px at the corners (k1 -0.3: DTU's lens is narrow, 31 degrees).
LENS = Lens("OPENCV", WIDTH, HEIGHT, (190.0, 190.0, 51.5, 38.7, -0.3, 0.1, 0.002, -0.001))
# The fisheye set: an equidistant lens (theta = r / f) long enough to stay within the pinhole photos.
FISHEYE = Lens("OPENCV_FISHEYE", WIDTH, HEIGHT, (188.0, 188.0, 51.5, 38.7, 0.05, -0.01, 0.002, 0.0))
POINTS = 60
SEED = 0


def pinhole_views() -> list[PinholeView]:
    """The fixture's DTU views with their pinhole cameras (IDR's K, skew dropped)."""
    scene = load_dtu(SOURCE, images="images_16", dtype=torch.float64)
    views = []
    for i, view in enumerate(VIEWS):
        K = scene.cameras.K[view]
        pinhole = Lens("PINHOLE", WIDTH, HEIGHT, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])))
        views.append(
            PinholeView(
                name=f"{i:06d}.png",
                image=scene.images[view],
                pinhole=pinhole,
                c2w=scene.cameras.c2w[view].numpy(),
                source=f"dtu_scan24/images_16/{scene.names[view]}",
            )
        )
    return views


def build(out: Path) -> None:
    views = pinhole_views()
    if out.exists():
        shutil.rmtree(out)
    # 3D points inside the object's sphere (radius 0.6), uniform in volume
    rng = np.random.default_rng(SEED)
    direction = rng.normal(size=(POINTS, 3))
    xyz = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0, 0.6, (POINTS, 1)) ** (1 / 3)
    write_lens_capture(out, views, LENS, colmap_text=True, points=xyz, instant_ngp=True)
    write_lens_capture(out / "fisheye", views, FISHEYE, colmap=False)  # nerfstudio's fisheye dialect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "distorted")
    build(parser.parse_args().out)


if __name__ == "__main__":
    main()
