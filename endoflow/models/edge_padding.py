"""Edge (replicate) padding that torch.compile can differentiate, and a 3x3 convolution that pads so.

Inductor's compiled backward of ``F.pad(mode="replicate")`` failed a stride assertion here (torch 2.13, CPU), so
under compilation the padding is built from border slices and concatenations, plain copies that any backend
handles and fuses into the convolution's input. Eager code keeps ``F.pad``: the two are equal to the bit, and on
2 CPU cores the paper model's step was 7% slower with the concatenations (two copies instead of one).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from endoflow.models.gemm_weight_grad import GemmWeightGradConv2d


def edge_pad(x: torch.Tensor, width: int = 1) -> torch.Tensor:
    """``x [..., H, W]`` with ``width`` copies of its border rows and columns around it: ``F.pad(x, (width,) * 4,
    mode="replicate")``, to the bit."""
    if width < 1:
        raise ValueError(f"padding width must be at least 1, got {width}")
    if not torch.compiler.is_compiling():
        return F.pad(x, (width,) * 4, mode="replicate")
    return sliced_edge_pad(x, width)


def sliced_edge_pad(x: torch.Tensor, width: int) -> torch.Tensor:
    """:func:`edge_pad` from border slices and concatenations (what compiled code uses)."""
    rows = torch.cat([x[..., :1, :]] * width + [x] + [x[..., -1:, :]] * width, dim=-2)
    return torch.cat([rows[..., :1]] * width + [rows] + [rows[..., -1:]] * width, dim=-1)


class EdgePaddedConv2d(GemmWeightGradConv2d):
    """A ``kernel_size`` x ``kernel_size`` (odd, at least 3) convolution keeping the map's size, padded by
    :func:`edge_pad`: ``nn.Conv2d(..., padding=kernel_size // 2, padding_mode="replicate")`` with the same
    parameters and names, its weight gradient on few positions as :class:`GemmWeightGradConv2d` takes it."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3) -> None:
        if kernel_size < 3 or kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd and at least 3 (a padded map keeps its size), got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._conv_forward(edge_pad(x, self.kernel_size[0] // 2), self.weight, self.bias)
