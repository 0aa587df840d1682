"""A 2-D convolution whose weight gradient, on maps of few positions on a CPU, is one matrix product.

oneDNN, which computes torch's CPU convolutions, is slow at one case the default model meets in every step: the
weight gradient of a wide convolution over a map of a few positions (ResNet-18's last stage sees 2x2 maps at
64 px). On 2 AVX2 cores (torch 2.13) that gradient of the 512 -> 512 3x3 convolution at batch 12 took 32 ms, the
same gradient as a product of the output's gradient and the unfolded input 4 ms; oneDNN took 23 ms even at batch 2.
On maps of more positions oneDNN is as fast or faster (at 4x4 the same time, at 30x30 0.31x the product's), so
only outputs of at most :data:`FEW_POSITIONS` positions take the product. The forward pass and the input's
gradient stay oneDNN's: the output is the same to the bit, the weight's gradient equal to rounding. See
``benchmarks/bench_step_versions.py`` for the training step's time with and without it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# Output maps of at most this many positions (2x2) take the matrix product for the weight's gradient.
FEW_POSITIONS = 4


def conv_weight_grad_by_gemm(x: torch.Tensor, grad_out: torch.Tensor, weight_shape: torch.Size,
                             stride: tuple[int, int], padding: tuple[int, int]) -> torch.Tensor:
    """The gradient of ``F.conv2d(x, weight, stride=stride, padding=padding)`` (groups 1, dilation 1) with respect
    to ``weight [O, C, kh, kw]``, given ``grad_out [B, O, Ho, Wo]``: the gradient times the unfolded input,
    summed over the batch and the positions in one matrix product."""
    out_channels, _, kh, kw = weight_shape
    columns = F.unfold(x, (kh, kw), padding=padding, stride=stride)  # [B, C * kh * kw, Ho * Wo]
    batch, patch, positions = columns.shape
    grad_rows = grad_out.reshape(batch, out_channels, positions).transpose(0, 1).reshape(out_channels, -1)
    return (grad_rows @ columns.transpose(1, 2).reshape(batch * positions, patch)).reshape(weight_shape)


class _ConvWithGemmWeightGrad(torch.autograd.Function):
    """``F.conv2d`` whose backward takes the weight's gradient from :func:`conv_weight_grad_by_gemm`."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None,
                stride: tuple[int, int], padding: tuple[int, int]) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.stride, ctx.padding, ctx.has_bias = stride, padding, bias is not None
        return F.conv2d(x, weight, bias, stride, padding)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        x, weight = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_x = torch.nn.grad.conv2d_input(x.shape, weight, grad_out, ctx.stride, ctx.padding)
        if ctx.needs_input_grad[1]:
            grad_weight = conv_weight_grad_by_gemm(x, grad_out, weight.shape, ctx.stride, ctx.padding)
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_bias = grad_out.sum(dim=(0, 2, 3))
        return grad_x, grad_weight, grad_bias, None, None


class GemmWeightGradConv2d(nn.Conv2d):
    """``nn.Conv2d`` (same arguments, parameters and names) whose weight gradient, where its output map has at
    most :data:`FEW_POSITIONS` positions on a CPU, is computed by :func:`conv_weight_grad_by_gemm` (see the
    module's docstring for why). Everywhere else, and always for the output, it is ``nn.Conv2d``."""

    def _conv_forward(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        if self._takes_gemm_weight_grad(x, weight):
            return _ConvWithGemmWeightGrad.apply(x, weight, bias, self.stride, self.padding)
        return super()._conv_forward(x, weight, bias)

    def _takes_gemm_weight_grad(self, x: torch.Tensor, weight: torch.Tensor) -> bool:
        plain = (self.groups == 1 and self.dilation == (1, 1) and self.padding_mode == "zeros"
                 and isinstance(self.padding, tuple) and x.dim() == 4)
        if not (plain and x.device.type == "cpu" and weight.requires_grad and torch.is_grad_enabled()):
            return False
        if torch.is_autocast_enabled("cpu") or torch.compiler.is_compiling():
            return False
        (kh, kw), (sh, sw), (ph, pw) = self.kernel_size, self.stride, self.padding
        out_h, out_w = (x.shape[-2] + 2 * ph - kh) // sh + 1, (x.shape[-1] + 2 * pw - kw) // sw + 1
        return out_h * out_w <= FEW_POSITIONS
