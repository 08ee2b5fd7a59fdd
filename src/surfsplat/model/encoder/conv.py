"""Convolution with replicate padding that keeps its input's dtype under autocast.

`nn.Conv2d(padding_mode="replicate")` pads with `F.pad`, which autocast runs in float32 on CPU: a
bf16 activation would be cast up for the padding and back down for the convolution, two full
copies that change nothing (padding is exact in any dtype). Same parameters and state-dict keys as
`nn.Conv2d`, and the same float32 computation.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from ...utils.precision import without_autocast


class ReplicateConv2d(nn.Conv2d):
    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, padding: int) -> None:
        super().__init__(in_channels, out_channels, kernel_size, padding=padding, padding_mode="replicate")

    def _conv_forward(self, input: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        with without_autocast(input.device.type):
            padded = F.pad(input, self._reversed_padding_repeated_twice, mode="replicate")
        return F.conv2d(padded, weight, bias, self.stride, 0, self.dilation, self.groups)
