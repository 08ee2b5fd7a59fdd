"""Training batches: a function of (seed, step), disjoint over ranks; the flip augmentation."""

from __future__ import annotations

import torch

from surfsplat.data.dataset import mix_seed
from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig, write_synthetic_chunks
from surfsplat.data.view_sampler import BoundedViewSamplerConfig
from surfsplat.train.config import DataConfig
from surfsplat.train.data import StepBatchSampler, ViewBatch, augment, build_train_batches, flip_views, to_train_batch


def test_ranks_split_the_global_batch_of_a_step() -> None:
    length, batch, seed = 10, 4, 3
    one = StepBatchSampler(length, batch, rank=0, world_size=1, seed=seed, start_step=0)
    two = [StepBatchSampler(length, batch, rank=r, world_size=2, seed=seed, start_step=0) for r in range(2)]
    it_one, it_two = iter(one), [iter(s) for s in two]
    seen: list[int] = []
    for _ in range(5):  # 20 samples = two epochs of 10
        full = next(it_one)
        halves = [next(i) for i in it_two]
        assert halves[0] + halves[1] == full  # rank 0 takes the first half of the same global batch
        seen += [index for index, _ in full]
    # Each epoch is a permutation: every sample exactly once per 10 positions.
    assert sorted(seen[:10]) == list(range(10)) and sorted(seen[10:]) == list(range(10))
    assert seen[:10] != seen[10:]  # epochs are shuffled differently


def test_resuming_at_a_step_gives_the_same_batches() -> None:
    first = iter(StepBatchSampler(7, 3, rank=1, world_size=3, seed=11, start_step=0))
    for _ in range(5):
        next(first)
    resumed = iter(StepBatchSampler(7, 3, rank=1, world_size=3, seed=11, start_step=5))
    assert [next(first) for _ in range(4)] == [next(resumed) for _ in range(4)]


def _views() -> ViewBatch:
    torch.manual_seed(0)
    b, v, h, w = 2, 2, 6, 8
    K = torch.tensor([[10.0, 0.0, 3.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]]).expand(b, v, 3, 3).clone()
    c2w = torch.eye(4).expand(b, v, 4, 4).clone()
    c2w[..., :3, 3] = torch.randn(b, v, 3)
    return ViewBatch(
        torch.rand(b, v, 3, h, w), c2w, K, torch.ones(b, v), torch.full((b, v), 9.0), torch.rand(b, v, 1, h, w)
    )


def test_flip_mirrors_images_and_cameras_consistently() -> None:
    views = _views()
    flipped = flip_views(views, torch.tensor([True, False]))
    assert torch.equal(flipped.images[0], views.images[0].flip(-1))
    assert torch.equal(flipped.depths[0], views.depths[0].flip(-1))
    assert torch.equal(flipped.images[1], views.images[1]) and torch.equal(flipped.c2w[1], views.c2w[1])
    # A world point seen at pixel x in the original appears at W - x in the mirrored view of the
    # mirrored world (x -> -x), at the same row and depth.
    point = torch.tensor([0.4, -0.2, 5.0, 1.0])
    mirrored = point * torch.tensor([-1.0, 1.0, 1.0, 1.0])

    def project(c2w: torch.Tensor, K: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        cam = torch.linalg.inv(c2w) @ p
        uvw = K @ cam[:3]
        return torch.stack([uvw[0] / uvw[2], uvw[1] / uvw[2], cam[2]])

    before = project(views.c2w[0, 1], views.K[0, 1], point)
    after = project(flipped.c2w[0, 1], flipped.K[0, 1], mirrored)
    torch.testing.assert_close(after, torch.stack([8 - before[0], before[1], before[2]]))


def test_augmentation_is_a_function_of_the_sample_key() -> None:
    views = _views()
    batch = to_train_batch(
        {
            "context": {"image": views.images, "c2w": views.c2w, "K": views.K, "near": views.near, "far": views.far},
            "target": {"image": views.images, "c2w": views.c2w, "K": views.K, "near": views.near, "far": views.far},
            "scene": ["a", "b"],
        },
        keys=[0, 0],
    )
    flips = []
    for key in range(64):
        batch.keys = [key, key + 1000]
        out = augment(batch, 0.5, seed=5)
        again = augment(batch, 0.5, seed=5)
        assert torch.equal(out.context.images, again.context.images)
        flipped = [not torch.equal(out.context.images[i], views.images[i]) for i in range(2)]
        # Context and target views of a sample flip together.
        assert flipped == [not torch.equal(out.target.images[i], views.images[i]) for i in range(2)]
        flips += flipped
    assert 40 <= sum(flips) <= 88  # about half of 128 coins
    assert augment(batch, 0.0, seed=5) is batch


def test_synthetic_batches_match_the_dataset() -> None:
    config = DataConfig(
        dataset="synthetic",
        image_shape=(16, 16),
        num_target_views=1,
        synthetic_length=3,
        synthetic_supersample=1,
        cache_samples=True,
    )
    source = build_train_batches(config, global_batch=2, rank=1, world_size=2, seed=4, start_step=2)
    batch = source.next(2)
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=3, image_shape=(16, 16), num_target_views=1, supersample=1, with_depth=False)
    )
    position = 2 * 2 + 1  # step 2, global batch 2, rank 1's single sample
    order = torch.randperm(3, generator=torch.Generator().manual_seed(mix_seed(4, position // 3))).tolist()
    expected = dataset[order[position % 3]]
    assert batch.keys == [position]
    assert torch.equal(batch.context.images[0], expected["context"]["image"])
    assert torch.equal(batch.target.c2w[0], expected["target"]["c2w"])


def test_chunk_stream_resumes_at_its_position(tmp_path) -> None:
    """A streamed chunk dataset: the batches after a saved position are those an uninterrupted
    stream yields (epochs included)."""
    write_synthetic_chunks(tmp_path / "chunks", num_scenes=3, image_shape=(16, 16), num_frames=6, supersample=1)
    config = DataConfig(
        dataset="chunks",
        roots=(str(tmp_path / "chunks"),),
        image_shape=(16, 16),
        num_target_views=1,
        near=0.5,
        far=15.0,
        view_sampler=BoundedViewSamplerConfig(
            num_target_views=1,
            min_distance_between_context_views=2,
            max_distance_between_context_views=4,
            warm_up_steps=0,
        ),
    )
    straight = build_train_batches(config, 1, 0, 1, seed=0, start_step=0)
    batches = [straight.next(step) for step in range(7)]  # more than two epochs of 3 scenes
    replay = build_train_batches(config, 1, 0, 1, seed=0, start_step=0)
    for step in range(4):
        replay.next(step)
    state = replay.state()
    assert state == {"kind": "stream", "epoch": 1, "batches": 1}
    resumed = build_train_batches(config, 1, 0, 1, seed=0, start_step=4, stream_state=state)
    for step in range(4, 7):
        got = resumed.next(step)
        assert got.scenes == batches[step].scenes and got.keys == batches[step].keys
        assert torch.equal(got.context.images, batches[step].context.images)
