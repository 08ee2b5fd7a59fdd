"""Writers of small scene folders and chunk examples, shared by the data-format, conversion and
error tests."""

from __future__ import annotations

import struct
from pathlib import Path

import torch
import torch.nn.functional as F
from PIL import Image

from surfsplat import Cameras
from surfsplat.data import (
    scene_to_example,
)
from surfsplat.data.posed_images import PosedImages
from surfsplat.data.synthetic.scene import WORLD_DOWN
from surfsplat.geometry.cameras import look_at, rigid_inverse
from surfsplat.geometry.rotations import matrix_to_quat


# ------------------------------------------------------------------------------------- helpers
def random_cameras(n: int, seed: int, width: int, height: int) -> Cameras:
    """Cameras on a circle around the origin looking at it (OpenCV), with distinct intrinsics."""
    g = torch.Generator().manual_seed(seed)
    angles = torch.linspace(0, 1.2, n, dtype=torch.float64)
    eyes = torch.stack(
        [3 * torch.sin(angles), 0.3 * torch.rand(n, generator=g, dtype=torch.float64) - 0.5, -3 * torch.cos(angles)], -1
    )
    forward = F.normalize(-eyes, dim=-1)
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64).expand_as(forward)  # world y down
    right = F.normalize(torch.linalg.cross(up, forward, dim=-1), dim=-1)
    down = torch.linalg.cross(forward, right, dim=-1)
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, forward, eyes
    K = torch.tensor(
        [[1.1 * width, 0.0, 0.47 * width], [0.0, 1.05 * width, 0.52 * height], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    return Cameras(c2w, K.repeat(n, 1, 1))


def write_images(folder: Path, names: list[str], width: int, height: int, seed: int, mode: str = "RGB") -> torch.Tensor:
    folder.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(seed)
    channels = len(mode)
    arrays = (torch.rand(len(names), height, width, channels, generator=g) * 255).to(torch.uint8)
    for name, arr in zip(names, arrays):
        Image.fromarray(arr.numpy(), mode=mode).save(folder / name)
    return arrays


# ------------------------------------------------------------------------------------- COLMAP
def write_colmap_model(
    folder: Path,
    cams: Cameras,
    names: list[str],
    width: int,
    height: int,
    binary: bool,
    model: str = "PINHOLE",
    extra: list[float] | None = None,
    points: torch.Tensor | None = None,
) -> None:
    """A COLMAP sparse model in COLMAP's own text or binary layout (one shared camera)."""
    folder.mkdir(parents=True, exist_ok=True)
    K = cams.K[0]
    params = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    if model == "SIMPLE_PINHOLE":
        params = [float(K[0, 0]), float(K[0, 2]), float(K[1, 2])]
    params += extra or []
    model_id = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "OPENCV": 4}[model]
    w2c = rigid_inverse(cams.c2w)
    quats = matrix_to_quat(w2c[:, :3, :3])
    n_points = 0 if points is None else len(points)
    # Every image observes every point (enough for near/far).
    if binary:
        with (folder / "cameras.bin").open("wb") as f:
            f.write(struct.pack("<Q", 1))
            f.write(struct.pack("<iiQQ", 1, model_id, width, height))
            f.write(struct.pack("<" + "d" * len(params), *params))
        with (folder / "images.bin").open("wb") as f:
            f.write(struct.pack("<Q", len(names)))
            for i, name in enumerate(names):
                f.write(struct.pack("<idddddddi", i + 1, *quats[i].tolist(), *w2c[i, :3, 3].tolist(), 1))
                f.write(name.encode() + b"\x00")
                f.write(struct.pack("<Q", n_points))
                for p in range(n_points):
                    f.write(struct.pack("<ddq", 1.0, 2.0, p + 1))
        if points is not None:
            with (folder / "points3D.bin").open("wb") as f:
                f.write(struct.pack("<Q", n_points))
                for p, xyz in enumerate(points.tolist()):
                    f.write(struct.pack("<QdddBBBd", p + 1, *xyz, 10, 20, 30, 0.5))
                    f.write(struct.pack("<Q", 1))
                    f.write(struct.pack("<ii", 1, p))
    else:
        lines = ["# Camera list", f"1 {model} {width} {height} " + " ".join(repr(v) for v in params)]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = ["# Image list with two lines of data per image:"]
        for i, name in enumerate(names):
            lines.append(
                " ".join(
                    [
                        str(i + 1),
                        *[repr(v) for v in quats[i].tolist()],
                        *[repr(v) for v in w2c[i, :3, 3].tolist()],
                        "1",
                        name,
                    ]
                )
            )
            lines.append(" ".join(f"1.0 2.0 {p + 1}" for p in range(n_points)))
        (folder / "images.txt").write_text("\n".join(lines) + "\n")
        if points is not None:
            rows = [f"{p + 1} {x!r} {y!r} {z!r} 10 20 30 0.5 1 {p}" for p, (x, y, z) in enumerate(points.tolist())]
            (folder / "points3D.txt").write_text("# 3D point list\n" + "\n".join(rows) + "\n")


def make_example(key: str, num_views: int, seed: int, size: tuple[int, int] = (12, 16)) -> dict:
    """A chunk example with random PNG images and cameras along a line (exactly known)."""
    g = torch.Generator().manual_seed(seed)
    h, w = size
    eyes = torch.stack([torch.linspace(0, 1, num_views), torch.zeros(num_views), torch.zeros(num_views)], -1)
    c2w = look_at(eyes.double(), eyes.double() + torch.tensor([0.2, 0.1, 5.0], dtype=torch.float64), WORLD_DOWN).float()
    K = torch.tensor([[1.2 * w, 0, w / 2], [0, 1.2 * w, h / 2], [0, 0, 1.0]]).repeat(num_views, 1, 1)
    scene = PosedImages(
        images=torch.rand(num_views, 3, h, w, generator=g),
        cameras=Cameras(c2w, K),
        names=[str(i) for i in range(num_views)],
    )
    return scene_to_example(scene, key=key, url=f"https://example.org/{key}", image_format="png")
