"""Shared fixtures: the read-only sample data and golden fixtures live beside the repository."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"sample data folder {SHARED} is absent (golden fixtures and captures live there)")
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
