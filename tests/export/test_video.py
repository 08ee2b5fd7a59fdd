"""MP4 writing: decoded frames match what was written; odd sizes; atomic writes; errors."""

from __future__ import annotations

import pytest
import torch

from surfsplat.export import video
from surfsplat.export.video import read_video, video_unavailable, write_video
from surfsplat.utils.checks import SurfSplatInputError

pytestmark = pytest.mark.skipif(video_unavailable() is not None, reason=str(video_unavailable()))


def _frames(t: int, h: int, w: int) -> torch.Tensor:
    """Smooth moving colour ramps (what H.264 encodes almost losslessly)."""
    y = torch.linspace(0, 1, h)[:, None].expand(h, w)
    x = torch.linspace(0, 1, w)[None, :].expand(h, w)
    return torch.stack(
        [torch.stack([(x + k / t) % 1 * 0.5 + 0.25, y * 0.8 + 0.1, 0.5 * (x + y) * (k + 1) / t]) for k in range(t)]
    )


def test_video_round_trip_matches_the_frames(tmp_path):
    frames = _frames(12, 48, 64)
    path = write_video(tmp_path / "clip.mp4", frames, fps=12)
    back = read_video(path)
    assert back.shape == frames.shape
    # Lossy H.264 of smooth ramps: a few grey levels of error at most on average.
    assert float((back - frames).abs().mean()) < 3 / 255
    # Frame order is kept: each decoded frame is closest to its own source frame.
    dist = ((back[:, None] - frames[None]) ** 2).mean(dim=(2, 3, 4))
    assert torch.equal(dist.argmin(dim=1), torch.arange(12))
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_odd_sizes_are_padded_not_resized(tmp_path):
    frames = _frames(4, 33, 51)
    back = read_video(write_video(tmp_path / "odd.mp4", frames, fps=8))
    assert back.shape == (4, 3, 34, 52)
    assert float((back[:, :, :33, :51] - frames).abs().mean()) < 4 / 255


def test_interrupted_video_leaves_nothing(tmp_path, monkeypatch):
    import imageio.v3 as iio

    def broken(path, *args, **kwargs):
        with open(path, "wb") as f:
            f.write(b"\x00\x00\x00\x18ftypmp42 partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(iio, "imwrite", broken)
    with pytest.raises(KeyboardInterrupt):
        write_video(tmp_path / "clip.mp4", _frames(2, 16, 16))
    assert list(tmp_path.iterdir()) == []


def test_video_errors(tmp_path, monkeypatch):
    with pytest.raises(SurfSplatInputError, match="expected a .mp4 file name"):
        write_video(tmp_path / "clip.gif", _frames(2, 16, 16))
    with pytest.raises(SurfSplatInputError, match="frames: expected shape"):
        write_video(tmp_path / "clip.mp4", torch.rand(2, 16, 16))
    with pytest.raises(SurfSplatInputError, match="fps"):
        write_video(tmp_path / "clip.mp4", _frames(2, 16, 16), fps=0)
    monkeypatch.setattr(video, "video_unavailable", lambda: "imageio-ffmpeg is not installed")
    with pytest.raises(SurfSplatInputError, match="cannot write MP4: imageio-ffmpeg is not installed"):
        write_video(tmp_path / "clip.mp4", _frames(2, 16, 16))
