"""Edge (replicate) padding written as concatenations of border slices, and a 3x3 convolution that pads so.

``F.pad(mode="replicate")`` computes the same values, but its CUDA kernels are slow on channels-last bf16 maps
(about 14 ms of the paper preset's 187 ms training step on an H200, forward and backward), and inductor's
compiled backward of it failed a stride check here (torch 2.13, CPU). Slices and concatenations are plain copies
that any backend handles, and compiled code fuses them into the convolution's input.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def edge_pad(x: torch.Tensor, width: int = 1) -> torch.Tensor:
    """``x [..., H, W]`` with ``width`` copies of its border rows and columns around it: ``F.pad(x, (width,) * 4,
    mode="replicate")``, to the bit."""
    if width < 1:
        raise ValueError(f"padding width must be at least 1, got {width}")
    rows = torch.cat([x[..., :1, :]] * width + [x] + [x[..., -1:, :]] * width, dim=-2)
    return torch.cat([rows[..., :1]] * width + [rows] + [rows[..., -1:]] * width, dim=-1)


class EdgePaddedConv2d(nn.Conv2d):
    """A ``kernel_size`` x ``kernel_size`` (odd, at least 3) convolution keeping the map's size, padded by :func:`edge_pad`:
    ``nn.Conv2d(..., padding=kernel_size // 2, padding_mode="replicate")`` with the same parameters and names."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3) -> None:
        if kernel_size < 3 or kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd and at least 3 (a padded map keeps its size), got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(edge_pad(x, self.kernel_size[0] // 2), self.weight, self.bias)
