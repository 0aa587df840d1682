"""The WGAN-GP critic for latent-bank pretraining: a residual CNN grown progressively with the generator.

One unbounded score per depth map (higher = more real). See docs/method.md, "Generative latent bank".
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from endoflow.models.latent_bank import GeneratorSpec
from endoflow.shapes import check_shape


class ResidualDown(nn.Module):
    """conv3x3 -> lrelu -> conv3x3 -> lrelu -> avgpool, plus a 1x1-conv avgpooled shortcut."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, in_channels, 3, padding=1)
        self.conv2 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.skip = nn.Conv2d(in_channels, out_channels, 1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.leaky_relu(self.conv1(x), 0.2)
        y = F.avg_pool2d(F.leaky_relu(self.conv2(y), 0.2), 2)
        # 1/sqrt(2) keeps the sum's variance that of either branch.
        return (y + F.avg_pool2d(self.skip(x), 2)) / math.sqrt(2)


def minibatch_stddev(x: torch.Tensor, group: int = 4) -> torch.Tensor:
    """Appends the mean over features of the per-group standard deviation as one extra channel."""
    b, c, h, w = x.shape
    g = min(group, b)
    while b % g:
        g -= 1
    y = x.reshape(g, -1, c, h, w)
    std = torch.sqrt(y.var(dim=0, unbiased=False) + 1e-8).mean(dim=(1, 2, 3))
    std = std.reshape(-1, 1, 1, 1).repeat(g, 1, h, w)
    return torch.cat([x, std], dim=1)


class Critic(nn.Module):
    """Scores depth maps ``[B, 1, r, r]`` -> ``[B]`` at any growing resolution r of ``spec``."""

    def __init__(self, spec: GeneratorSpec) -> None:
        super().__init__()
        self.spec = spec
        res = self.spec.resolutions
        self.from_depth = nn.ModuleList([nn.Conv2d(1, self.spec.channels(r), 1) for r in res])
        # downs[i] takes resolution res[i] to res[i - 1]; downs[0] is unused and left out.
        self.downs = nn.ModuleList(
            [ResidualDown(self.spec.channels(r), self.spec.channels(r // 2)) for r in res[1:]]
        )
        c0 = self.spec.channels(res[0])
        self.final_conv = nn.Conv2d(c0 + 1, c0, 3, padding=1)
        self.final_linear = nn.Linear(c0 * res[0] * res[0], 1)
        # He initialisation for leaky ReLU: with PyTorch's default the input gradient of a fresh critic
        # is ~1e-4 at 64 px, so the gradient penalty (target norm 1) spends the early training
        # just scaling the critic up while the generator runs ahead of it.
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_normal_(m.weight, a=0.2)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, depth: torch.Tensor, resolution: int | None = None, alpha: float = 1.0) -> torch.Tensor:
        resolution = resolution or self.spec.resolution
        if resolution not in self.spec.resolutions:
            raise ValueError(f"resolution {resolution} not in {self.spec.resolutions}")
        check_shape("depth", depth, "B,1,H,W", H=resolution, W=resolution)
        level = self.spec.resolutions.index(resolution)
        x = F.leaky_relu(self.from_depth[level](depth), 0.2)
        if level > 0:
            x = self.downs[level - 1](x)
            if alpha < 1.0:
                coarse = F.leaky_relu(self.from_depth[level - 1](F.avg_pool2d(depth, 2)), 0.2)
                x = alpha * x + (1 - alpha) * coarse
        for i in range(level - 1, 0, -1):
            x = self.downs[i - 1](x)
        x = F.leaky_relu(self.final_conv(minibatch_stddev(x)), 0.2)
        return self.final_linear(x.flatten(1)).squeeze(1)
