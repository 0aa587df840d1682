"""PoseNet: a pair encoder with Gaussian heads over the 6-DoF relative pose (the paper's VAE encoder).

``forward(target, source)`` returns the mean and log-variance (``None`` without ``pose_vae``) of the pose vector
``(rx, ry, rz, tx, ty, tz)`` (axis-angle in radians, cm) of ``T_source_target``. See docs/method.md,
"VAE-constrained PoseNet".
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from endoflow.models.gemm_weight_grad import GemmWeightGradConv2d
from endoflow.models.resnet_encoder import ResNetEncoder
from endoflow.shapes import check_shape

MEAN_SCALE = 0.01


class PoseNet(nn.Module):
    def __init__(self, pose_vae: bool, encoder_weights: str | None = None, logvar_init: float = -9.0) -> None:
        super().__init__()
        self.encoder = ResNetEncoder(num_images=2, weights=encoder_weights)
        self.squeeze = GemmWeightGradConv2d(ResNetEncoder.channels[-1], 256, 1)
        self.trunk = nn.Sequential(
            GemmWeightGradConv2d(256, 256, 3, padding=1), nn.ReLU(),
            GemmWeightGradConv2d(256, 256, 3, padding=1), nn.ReLU(),
        )
        self.mean_head = GemmWeightGradConv2d(256, 6, 1)
        self.logvar_head = GemmWeightGradConv2d(256, 6, 1) if pose_vae else None
        if self.logvar_head is not None:
            nn.init.normal_(self.logvar_head.weight, std=1e-3)
            nn.init.constant_(self.logvar_head.bias, logvar_init)

    @property
    def pose_vae(self) -> bool:
        return self.logvar_head is not None

    def forward(self, target: torch.Tensor, source: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``target, source [B, 3, H, W]`` in [0, 1] -> (``mean [B, 6]``, ``logvar [B, 6]`` or ``None``)."""
        check_shape("source", source, "B,3,H,W", **check_shape("target", target, "B,3,H,W"))
        x = self.encoder(torch.cat([target, source], dim=1))[-1]
        x = self.trunk(F.relu(self.squeeze(x)))
        mean = MEAN_SCALE * self.mean_head(x).mean(dim=(2, 3))
        logvar = self.logvar_head(x).mean(dim=(2, 3)) if self.logvar_head is not None else None
        return mean, logvar
