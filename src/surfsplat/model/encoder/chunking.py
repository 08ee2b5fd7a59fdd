"""Working through the largest tensors a few items at a time on CPU.

glibc serves blocks above its mmap threshold (32 MiB at most) as fresh memory mappings, which are
page-faulted in on every call; in a VM that costs about as much as the arithmetic filling them.
On CPU the encoder therefore computes its largest temporaries (the transformer MLP's hidden layer,
the full-resolution DPT and Gaussian head) a few views at a time, each block below that bound.
Items are independent, so the outputs are the same; on GPUs the caching allocator makes this
unnecessary and whole batches run at once.
"""

from __future__ import annotations

import torch

CPU_BLOCK_BYTES = 32 * 2**20  # glibc's largest mmap threshold on 64-bit systems


def items_per_block(count: int, bytes_per_item: int, device: torch.device) -> int:
    """How many of `count` items to process together so that their largest tensor, of
    `bytes_per_item` bytes per item, stays below CPU_BLOCK_BYTES (at least one item)."""
    if device.type != "cpu":
        return count
    return max(1, min(count, (CPU_BLOCK_BYTES - 1) // max(bytes_per_item, 1)))
