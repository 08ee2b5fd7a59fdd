"""Shared fixtures.

The full sample captures and golden fixtures live beside the repository (`../shared`, present on CI);
reduced copies built from them by `tests/data/make_fixtures.py` are part of the repository, so a clone
runs every proof of the math and every data-format test on those (see tests/data/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
FIXTURES = Path(__file__).resolve().parent / "data"

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(
            f"full sample data and golden fixtures {SHARED} are absent (needed here; tests/data has reduced copies)"
        )
    return SHARED


@pytest.fixture(scope="session")
def golden_dir(shared_dir: Path) -> Path:
    path = shared_dir / "golden"
    if not path.is_dir():
        pytest.skip(f"golden fixtures {path} are absent")
    return path


@pytest.fixture(scope="session")
def data_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data"
    if not path.is_dir():
        pytest.skip(f"sample captures {path} are absent")
    return path


@dataclass(frozen=True)
class Samples:
    """A folder holding `llff_fern`, `dtu_scan24` and `eval_index`, with the facts tests pin about it."""

    root: Path
    full: bool  # the full samples in ../shared/data, not the reduced copies in tests/data
    fern_images: str  # image folder name
    fern_views: int
    fern_size: tuple[int, int]  # (H, W)
    fern_factor: int  # downscale from the 4032x3024 photos
    dtu_images: str
    dtu_views: int
    dtu_size: tuple[int, int]  # (H, W)
    dtu_factor: int  # downscale from DTU's 1600x1200 sensor


FULL_SAMPLES = Samples(SHARED / "data", True, "images_8", 20, (378, 504), 8, "images_4", 49, (300, 400), 4)
REDUCED_SAMPLES = Samples(FIXTURES, False, "images_16", 6, (189, 252), 16, "images_16", 24, (75, 100), 16)


@pytest.fixture(scope="session", params=["reduced", "full"])
def samples(request) -> Samples:
    """The reduced captures in tests/data always, and the full ones where ../shared/data is present."""
    if request.param == "reduced":
        return REDUCED_SAMPLES
    if not FULL_SAMPLES.root.is_dir():
        pytest.skip(f"full sample data {FULL_SAMPLES.root} is absent (the reduced copy in tests/data ran instead)")
    return FULL_SAMPLES


@pytest.fixture(scope="session")
def preferred_samples() -> Samples:
    """The full samples where present, else the reduced copy: for slow end-to-end runs, which either
    proves (running both would double their time)."""
    return FULL_SAMPLES if FULL_SAMPLES.root.is_dir() else REDUCED_SAMPLES


@pytest.fixture(scope="session")
def golden_subset_dir() -> Path:
    """Reduced golden fixtures in the repository: exact inputs, a fixed random subset of the outputs."""
    return FIXTURES / "golden"


@dataclass(frozen=True)
class GoldenSubset:
    """The golden encoder case as the repository keeps it (tests/data/README.md).

    tensors: `context.*` exact (the image rebuilt from view 0 and the columns view 1 adds),
        `outputs.*` at the Gaussians `rows` (depths flattened the same way, view, row, column),
        `intermediates.NAME` at the flat element indices `index.NAME`, and `crop.*`: the
        gaussian_head_out and depths of the top-left `crop` x `crop` pixels of both views.
    shapes: full shape of every `outputs.*` and `intermediates.*` tensor.
    """

    tensors: dict[str, torch.Tensor]
    shapes: dict[str, tuple[int, ...]]
    crop: int


@pytest.fixture(scope="session")
def golden_subset(golden_subset_dir: Path) -> GoldenSubset:
    from safetensors import safe_open

    with safe_open(str(golden_subset_dir / "case_identity_subset.safetensors"), framework="pt") as f:
        tensors = {k: f.get_tensor(k) for k in f.keys()}
        meta = f.metadata()
    # View 1 is view 0 shifted left by `shift` pixels; only its new right-hand columns are stored.
    shift = int(meta["shift"])
    view0, right = tensors.pop("context.image_view0"), tensors.pop("context.image_view1_right")
    view1 = torch.cat([view0[..., shift:], right], dim=-1)
    tensors["context.image"] = torch.stack([view0, view1])[None]  # [1, 2, 3, H, W]
    shapes = {
        k.removeprefix("shape."): tuple(int(n) for n in v.split(",")) for k, v in meta.items() if k.startswith("shape.")
    }
    return GoldenSubset(tensors, shapes, int(meta["crop"]))


@pytest.fixture(scope="module")
def one_torch_thread():
    """One intra-op torch thread for a module of many small elementwise ops: on a loaded 2-core
    machine two threads spend more time in barriers than computing (measured 15x slower)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def lpips_files(tmp_path_factory) -> tuple[Path, Path]:
    """Random LPIPS weights in torchvision's and the lpips package's file layouts: for wiring and
    structural checks only, never a reported number."""
    from surfsplat.metrics.lpips import VGG16_FILENAME, lin_shapes, vgg_shapes

    g = torch.Generator().manual_seed(0)
    folder = tmp_path_factory.mktemp("lpips")
    torch.save({k: 0.1 * torch.randn(s, generator=g) for k, s in vgg_shapes().items()}, folder / VGG16_FILENAME)
    torch.save({k: torch.rand(s, generator=g) for k, s in lin_shapes().items()}, folder / "vgg.pth")
    return folder / VGG16_FILENAME, folder / "vgg.pth"
