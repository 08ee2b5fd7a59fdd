"""RealEstate10K-style chunks, evaluation indices, view samplers and the streaming dataset."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader

import surfsplat.data.chunks as chunks_module
import surfsplat.data.dataset as dataset_module
from surfsplat import Cameras
from surfsplat.data import (
    BoundedViewSampler,
    BoundedViewSamplerConfig,
    ChunkDataset,
    ChunkDatasetConfig,
    EvaluationIndex,
    EvaluationViewSampler,
    NotEnoughViews,
    StepCounter,
    example_to_scene,
    load_example,
    load_scene,
    read_chunk,
    read_index,
    scene_to_example,
    write_chunks,
)
from surfsplat.data.posed_images import PosedImages
from tests.helpers.data import make_example


def _dataset(root: Path, sampler, **kw) -> ChunkDataset:
    return ChunkDataset(ChunkDatasetConfig(roots=[root], image_shape=None, **kw), sampler)


def _small_sampler(**kw) -> BoundedViewSampler:
    cfg = dict(min_distance_between_context_views=2, max_distance_between_context_views=4, warm_up_steps=0)
    cfg.update(kw)
    return BoundedViewSampler(BoundedViewSamplerConfig(**cfg))


# ------------------------------------------------------------------------------ writer/reader
def test_chunk_round_trip_is_exact(tmp_path: Path) -> None:
    examples = [make_example(f"scene{i}", 3 + i, seed=i) for i in range(5)]
    bytes_per = sum(t.numel() for t in examples[0]["images"])
    index = write_chunks(examples, tmp_path, target_bytes=2 * bytes_per)
    files = sorted(p.name for p in tmp_path.glob("*.torch"))
    assert len(files) >= 2 and set(index.values()) == set(files)
    assert {k: v.name for k, v in read_index(tmp_path).items()} == index
    back = [ex for name in files for ex in read_chunk(tmp_path / name)]
    assert [e["key"] for e in back] == [e["key"] for e in examples]
    for a, b in zip(examples, back):
        assert a["url"] == b["url"]
        assert torch.equal(a["timestamps"], b["timestamps"]) and torch.equal(a["cameras"], b["cameras"])
        assert all(torch.equal(x, y) for x, y in zip(a["images"], b["images"]))
    ex = load_example(tmp_path, "scene3")
    assert ex["cameras"].shape == (6, 18)
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporary files left


def test_png_example_decodes_to_the_written_pixels() -> None:
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (2, 3, 10, 14), generator=g).float() / 255
    cams = Cameras(torch.eye(4).repeat(2, 1, 1), torch.tensor([[20.0, 0, 7], [0, 20, 5], [0, 0, 1]]).repeat(2, 1, 1))
    ex = scene_to_example(PosedImages(images, cams, ["0", "1"]), key="k", image_format="png")
    back = example_to_scene(ex)
    assert torch.equal(back.images, images)
    torch.testing.assert_close(back.cameras.K, cams.K)


def test_fern_chunk_loads_through_the_re10k_path(samples, tmp_path: Path) -> None:
    fern = load_scene(samples.root / "llff_fern")
    write_chunks([scene_to_example(fern, key="fern", image_format="png")], tmp_path)
    index = EvaluationIndex.from_dict({"fern": {"context": [0, 5], "target": [2, 3, 4]}})
    ds = _dataset(tmp_path, EvaluationViewSampler(index))
    (sample,) = list(ds)
    ctx, tgt = sample["context"], sample["target"]
    assert sample["scene"] == "fern" and ctx["index"].tolist() == [0, 5]
    # PNG keeps 8-bit pixels exactly; cameras go through float32 normalized rows.
    assert torch.equal(ctx["image"], fern.images[[0, 5]])
    torch.testing.assert_close(ctx["c2w"], fern.cameras.c2w[[0, 5]], atol=2e-5, rtol=0)
    torch.testing.assert_close(tgt["K"], fern.cameras.K[[2, 3, 4]], atol=1e-4, rtol=1e-6)
    # JPEG, as the RealEstate10K releases store frames: same cameras, images within JPEG error.
    jpeg_dir = tmp_path / "jpeg"
    write_chunks([scene_to_example(fern.select([0, 1]), key="fern", image_format="jpeg", quality=95)], jpeg_dir)
    back = example_to_scene(load_example(jpeg_dir, "fern"))
    mse = float(((back.images - fern.images[:2]) ** 2).mean())
    assert mse < 10 ** (-30 / 10)
    torch.testing.assert_close(back.cameras.c2w, fern.cameras.c2w[:2], atol=2e-5, rtol=0)


# ----------------------------------------------------------------------------- evaluation index
# (entries, excluded) of the release files, and of their reduced copies in tests/data.
EVAL_INDEX_SIZES = {
    True: {"re10k": (7194, 720), "acid": (1848, 253), "dl3dv": 140},
    False: {"re10k": (7, 2), "acid": (7, 2), "dl3dv": 6},
}


def test_release_evaluation_indices_load(samples) -> None:
    folder = samples.root / "eval_index"
    sizes = EVAL_INDEX_SIZES[samples.full]
    re10k = EvaluationIndex.load(folder / "evaluation_index_re10k.json")
    assert (len(re10k), re10k.num_excluded) == sizes["re10k"]
    acid = EvaluationIndex.load(folder / "evaluation_index_acid.json")
    assert (len(acid), acid.num_excluded) == sizes["acid"]
    entry = re10k.entries["5aca87f95a9412c6"]
    assert entry.context == (58, 133) and entry.target == (84, 102, 129)
    dtu = EvaluationIndex.load(folder / "evaluation_index_dtu_nctx3.json")
    entries = dtu.lookup("scan1_train")  # the chunk key of MVSplat's DTU conversion
    assert [k for k, _ in entries] == [f"scan1_train_{i:02d}" for i in range(4)]
    assert all(len(e.context) == 3 and len(e.target) == 1 for _, e in entries)
    dl3dv = EvaluationIndex.load(folder / "dl3dv_start_0_distance_10_ctx_2v_tgt_4v.json")
    assert len(dl3dv) == sizes["dl3dv"] and all(len(e.target) == 4 for e in dl3dv.entries.values())
    scannet = EvaluationIndex.load(folder / "evaluation_index_scannet.json")
    assert "scene0707_00_slice00" in scannet and dtu.lookup("scan999") == []


# --------------------------------------------------------------------------------- view sampler
def test_bounded_sampler_warm_up_schedule() -> None:
    sampler = BoundedViewSampler()  # RealEstate10K settings
    assert sampler.gap_range(0) == (25, 45)
    assert sampler.gap_range(15_000) == (35, 90)
    assert sampler.gap_range(30_000) == (45, 135)
    assert sampler.gap_range(90_000) == (45, 135)


def test_bounded_sampler_draws_within_bounds() -> None:
    step = StepCounter(30_000)
    sampler = BoundedViewSampler(step=step)
    g = torch.Generator().manual_seed(0)
    gaps = []
    for _ in range(300):
        context, target = sampler.sample(300, g)
        left, right = context.tolist()
        gaps.append(right - left)
        assert 45 <= right - left <= 135 and 0 <= left and right < 300
        assert target.shape == (4,) and bool(((target >= left) & (target <= right)).all())
    assert min(gaps) < 55 and max(gaps) > 125  # the whole range is used
    step.set(0)
    assert all(25 <= int(torch.diff(sampler.sample(300, g)[0])) <= 45 for _ in range(50))
    with pytest.raises(NotEnoughViews, match="too few"):
        BoundedViewSampler(step=StepCounter(30_000)).sample(40, g)  # 39 < 45
    three = BoundedViewSampler(BoundedViewSamplerConfig(num_context_views=3, warm_up_steps=0))
    for _ in range(50):
        c, _ = three.sample(200, g)
        assert c[0] < c[1] < c[2]


# ------------------------------------------------------------------------------- chunk dataset
def test_dataset_streams_one_chunk_at_a_time_and_decodes_only_sampled_views(tmp_path: Path, monkeypatch) -> None:
    write_chunks([make_example(f"s{i}", 20, seed=i) for i in range(3)], tmp_path, target_bytes=1)
    reads, decodes = [], []
    real_read, real_decode = dataset_module.read_chunk, chunks_module.decode_image_bytes
    monkeypatch.setattr(dataset_module, "read_chunk", lambda p: reads.append(p) or real_read(p))
    monkeypatch.setattr(chunks_module, "decode_image_bytes", lambda *a, **k: decodes.append(1) or real_decode(*a, **k))
    it = iter(_dataset(tmp_path, _small_sampler()))
    sample = next(it)
    assert len(reads) == 1  # the rest of the dataset is not touched yet
    assert len(decodes) == len(set(sample["context"]["index"].tolist()) | set(sample["target"]["index"].tolist())) <= 6
    rest = list(it)
    assert len(reads) == 3 and len(rest) == 2
    keys = {sample["scene"]} | {s["scene"] for s in rest}
    assert keys == {"s0", "s1", "s2"}
    # Samples carry the documented layout, with cameras consistent with the source example.
    ex = load_example(tmp_path, sample["scene"])
    cams = example_to_scene(ex).cameras
    idx = sample["target"]["index"]
    torch.testing.assert_close(sample["target"]["c2w"], cams.c2w[idx])
    assert sample["context"]["near"].tolist() == [0.5, 0.5] and sample["context"]["far"].tolist() == [100.0, 100.0]


def test_dataset_rescale_and_crop_keeps_intrinsics(tmp_path: Path) -> None:
    write_chunks([make_example("wide", 8, seed=0, size=(30, 60))], tmp_path)
    ds = ChunkDataset(ChunkDatasetConfig(roots=[tmp_path], image_shape=(16, 16), shuffle=False), _small_sampler())
    (sample,) = list(ds)
    assert sample["context"]["image"].shape == (2, 3, 16, 16)
    # K = [[72, 0, 30], [0, 72, 15], [0, 0, 1]] at 30x60 -> scaled by 16/30 to 16x32 -> centre crop
    # of 16 columns starting at column 8.
    s = 16 / 30
    expected = torch.tensor([[72 * s, 0, 30 * s - 8], [0, 72 * s, 15 * s], [0, 0, 1]])
    torch.testing.assert_close(sample["context"]["K"][0], expected, atol=1e-4, rtol=0)


def _keys_seen(root: Path, world_size: int, workers: int) -> list[list[str]]:
    per_rank = []
    for rank in range(world_size):
        ds = ChunkDataset(
            ChunkDatasetConfig(roots=[root], image_shape=None, seed=3),
            _small_sampler(),
            rank=rank,
            world_size=world_size,
        )
        loader = DataLoader(ds, batch_size=None, num_workers=workers)
        per_rank.append([s["scene"] for s in loader])
    return per_rank


@pytest.mark.parametrize("examples_per_chunk", [1, 8])
def test_ranks_and_workers_see_disjoint_data(tmp_path: Path, examples_per_chunk: int) -> None:
    examples = [make_example(f"s{i}", 6, seed=i, size=(4, 4)) for i in range(8)]
    target = 1 if examples_per_chunk == 1 else 10**9
    write_chunks(examples, tmp_path, target_bytes=target)
    assert len(list(tmp_path.glob("*.torch"))) == (8 if examples_per_chunk == 1 else 1)
    per_rank = _keys_seen(tmp_path, world_size=2, workers=2)
    seen = [k for keys in per_rank for k in keys]
    assert sorted(seen) == sorted(f"s{i}" for i in range(8))  # every example exactly once
    assert all(len(keys) == 4 for keys in per_rank)


def test_evaluation_sampler_in_dataset_counts_what_it_skips(tmp_path: Path, caplog) -> None:
    write_chunks([make_example(k, 6, seed=i) for i, k in enumerate(["a", "b", "c", "d"])], tmp_path)
    index = EvaluationIndex.from_dict(
        {
            "a": {"context": [0, 4], "target": [1, 2]},
            "b": None,
            "d": {"context": [0, 9], "target": [3]},  # view 9 does not exist
        },
        source="index.json",
    )
    ds = ChunkDataset(
        ChunkDatasetConfig(roots=[tmp_path], image_shape=None, shuffle=False), EvaluationViewSampler(index)
    )
    with caplog.at_level("WARNING", logger="surfsplat.data"):
        samples = list(ds)
    assert [s["scene"] for s in samples] == ["a"]
    assert samples[0]["context"]["index"].tolist() == [0, 4] and samples[0]["target"]["index"].tolist() == [1, 2]
    summary = ds.summary
    assert summary.yielded == 1
    assert dict(summary.skipped) == {
        "excluded by evaluation index": 1,
        "not in evaluation index": 1,
        "index out of range": 1,
    }
    assert any("uses view 9 but scene 'd' has 6 views" in m for m in summary.messages)
    assert "3 skipped" in caplog.text


def test_dataset_from_index_json_and_shuffle_is_an_epoch_permutation(tmp_path: Path) -> None:
    write_chunks([make_example(f"s{i}", 6, seed=i, size=(4, 4)) for i in range(6)], tmp_path, target_bytes=1)
    ds = ChunkDataset(ChunkDatasetConfig(roots=[tmp_path], image_shape=None, use_index=True, seed=1), _small_sampler())
    first = [s["scene"] for s in ds]
    again = [s["scene"] for s in ds]
    ds.set_epoch(1)
    other = [s["scene"] for s in ds]
    assert first == again and sorted(first) == sorted(other) == [f"s{i}" for i in range(6)]
    assert first != other
    assert json.loads((tmp_path / "index.json").read_text())["s0"] == "000000.torch"
