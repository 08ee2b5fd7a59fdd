"""Build `tests/data/distorted/`: DTU views as a camera with a lens would have taken them.

    python tests/data/make_distorted.py [--out tests/data/distorted]

Deterministic (fixed views, fixed seed); it reads only the repository's own DTU fixture
(`tests/data/dtu_scan24`), so it runs in any clone. The five first views of that fixture (100x75,
pinhole, IDR cameras) are resampled to one OPENCV lens (`LENS` below, known coefficients) by
`surfsplat.data.undistort.distort` (bicubic), and written as the captures the readers meet:
- `images/000000.png` ... the distorted photos (8-bit RGB);
- `sparse/0/` a COLMAP model written by pycolmap (`Reconstruction.write`, binary: cameras, images,
  points3D, rigs, frames), `sparse/text/` the same model by `Reconstruction.write_text`; one OPENCV
  camera, the views' poses, and 3D points (random, inside the object's sphere) observed where the
  lens projects them;
- `transforms.json`: nerfstudio's dialect (camera_model OPENCV, fl_x, fl_y, cx, cy, w, h, k1, k2, p1,
  p2 at the top level; frames' transform_matrix camera-to-world with OpenGL axes);
- `instant_ngp/transforms.json`: instant-ngp's dialect (no camera_model; k1, k2, p1, p2 at the top
  level; w and h floats; fl_x without fl_y; camera_angle_x; paths relative to its folder);
- `truth.json`: the lens, and per view the source photo, its pinhole K (IDR's, skew dropped) and its
  camera-to-world (OpenCV axes), so a reader's undistortion can be checked against the source;
- `fisheye/`: the same views through an OPENCV_FISHEYE lens (`FISHEYE`), with nerfstudio's
  `transforms.json` (camera_model OPENCV_FISHEYE, k1..k4) and its own `truth.json`.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import torch
from PIL import Image

from surfsplat.data.formats.dtu import load_dtu
from surfsplat.data.undistort import distort
from surfsplat.geometry.lens import Lens, project

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


def _png(image: torch.Tensor, path: Path) -> None:
    array = (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    Image.fromarray(array).save(path, optimize=False)


def _gl(c2w: np.ndarray) -> list[list[float]]:
    """OpenCV camera axes (x right, y down, z forward) -> OpenGL's (x right, y up, z back)."""
    out = c2w.copy()
    out[:3, 1:3] *= -1
    return [[round(float(v), 12) for v in row] for row in out]


def _distort_views(scene, lens: Lens, folder: Path, names: list[str]) -> list[dict]:
    """Write each view's photo as `lens` sees it into folder/images; the views' truth."""
    (folder / "images").mkdir(parents=True)
    views = []
    for name, view in zip(names, VIEWS):
        K = scene.cameras.K[view]
        pinhole = Lens("PINHOLE", WIDTH, HEIGHT, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])))
        cover = distort(torch.ones(1, HEIGHT, WIDTH), pinhole, lens)
        assert bool((cover == 1).all()), f"view {view}: the lens sees beyond the pinhole photo"
        _png(distort(scene.images[view].to(torch.float32), pinhole, lens, "bicubic"), folder / "images" / name)
        views.append(
            {
                "image": f"images/{name}",
                "source": f"dtu_scan24/images_16/{scene.names[view]}",
                "pinhole": pinhole.to_dict(),
                "c2w": [[float(v) for v in row] for row in scene.cameras.c2w[view].numpy()],
            }
        )
    return views


def build(out: Path) -> None:
    scene = load_dtu(SOURCE, images="images_16", dtype=torch.float64)
    if out.exists():
        shutil.rmtree(out)
    names = [f"{i:06d}.png" for i in range(len(VIEWS))]
    fx, fy, cx, cy = LENS.focal_and_centre
    truth_views = _distort_views(scene, LENS, out, names)
    c2ws = [scene.cameras.c2w[view].numpy() for view in VIEWS]

    # COLMAP: one OPENCV camera, a trivial rig and frame per image (COLMAP >= 3.12's layout)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="OPENCV", width=WIDTH, height=HEIGHT, params=list(LENS.params), camera_id=1)
    )
    rng = np.random.default_rng(SEED)
    direction = rng.normal(size=(POINTS, 3))
    xyz = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0, 0.6, (POINTS, 1)) ** (1 / 3)
    observations: dict[int, list[tuple[int, np.ndarray]]] = {}
    for image_id, (name, c2w) in enumerate(zip(names, c2ws), start=1):
        w2c = np.linalg.inv(c2w)
        cam = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        px = project(LENS, torch.from_numpy(cam)).numpy()
        seen = np.isfinite(px).all(1) & (px[:, 0] > 0) & (px[:, 0] < WIDTH) & (px[:, 1] > 0) & (px[:, 1] < HEIGHT)
        keypoints = px[seen]
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
        for idx, point in enumerate(np.nonzero(seen)[0]):
            observations.setdefault(int(point), []).append((image_id, idx))
    for point in sorted(observations):
        track = pycolmap.Track()
        for image_id, idx in observations[point]:
            track.add_element(image_id, idx)
        rec.add_point3D(xyz[point], track, np.array([128, 128, 128], dtype=np.uint8))
    (out / "sparse" / "0").mkdir(parents=True)
    (out / "sparse" / "text").mkdir(parents=True)
    rec.write(str(out / "sparse" / "0"))
    rec.write_text(str(out / "sparse" / "text"))

    frames = [{"file_path": f"images/{name}", "transform_matrix": _gl(c2w)} for name, c2w in zip(names, c2ws)]
    k1, k2, p1, p2 = LENS.extra_params
    nerfstudio = {
        "camera_model": "OPENCV",
        **{"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": WIDTH, "h": HEIGHT},
        **{"k1": k1, "k2": k2, "p1": p1, "p2": p2},
        "frames": frames,
    }
    (out / "transforms.json").write_text(json.dumps(nerfstudio, indent=2) + "\n")
    (out / "instant_ngp").mkdir()
    ngp = {
        "camera_angle_x": 2 * math.atan(WIDTH / (2 * fx)),
        **{"fl_x": fx, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "cx": cx, "cy": cy},
        **{"w": float(WIDTH), "h": float(HEIGHT), "aabb_scale": 4},
        "frames": [{**f, "file_path": f"../{f['file_path']}", "sharpness": 100.0} for f in frames],
    }
    (out / "instant_ngp" / "transforms.json").write_text(json.dumps(ngp, indent=2) + "\n")
    truth = {"lens": LENS.to_dict(), "resampling": "surfsplat.data.undistort.distort, bicubic", "views": truth_views}
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")

    # nerfstudio's fisheye dialect: the same views through an OPENCV_FISHEYE lens
    fisheye = out / "fisheye"
    fish_views = _distort_views(scene, FISHEYE, fisheye, names)
    ffx, ffy, fcx, fcy = FISHEYE.focal_and_centre
    f1, f2, f3, f4 = FISHEYE.extra_params
    nerfstudio_fisheye = {
        "camera_model": "OPENCV_FISHEYE",
        **{"fl_x": ffx, "fl_y": ffy, "cx": fcx, "cy": fcy, "w": WIDTH, "h": HEIGHT},
        **{"k1": f1, "k2": f2, "k3": f3, "k4": f4},
        "frames": frames,
    }
    (fisheye / "transforms.json").write_text(json.dumps(nerfstudio_fisheye, indent=2) + "\n")
    truth = {"lens": FISHEYE.to_dict(), "resampling": "surfsplat.data.undistort.distort, bicubic", "views": fish_views}
    (fisheye / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "distorted")
    build(parser.parse_args().out)


if __name__ == "__main__":
    main()
