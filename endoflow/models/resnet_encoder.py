"""ResNet-18 encoder (He et al. 2016) returning features at five resolutions, as Monodepth2 uses it.

Written here (no torchvision), with the common ResNet-18 parameter names, so that an ImageNet state dict saved
locally loads (:func:`load_imagenet_weights`). See docs/method.md, "DepthNet".
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from endoflow.config import ENCODER_STRIDE
from endoflow.errors import DataFormatError
from endoflow.io import load_plain_torch_file
from endoflow.models.gemm_weight_grad import GemmWeightGradConv2d
from endoflow.shapes import check_shape

# Feature channels at strides 2, 4, 8, 16, 32.
CHANNELS = (64, 64, 128, 256, 512)
# ImageNet-style input normalisation used by Monodepth2 for images in [0, 1].
MEAN, STD = 0.45, 0.225


class BasicBlock(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = GemmWeightGradConv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = GemmWeightGradConv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(
                GemmWeightGradConv2d(in_channels, out_channels, 1, stride=stride, bias=False),
                nn.BatchNorm2d(out_channels),
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNetEncoder(nn.Module):
    """ResNet-18 on ``[B, 3 * num_images, H, W]`` images in [0, 1], H and W divisible by 32.

    Returns five feature maps, finest first: ``[B, 64, H/2, W/2]``, ``[B, 64, H/4, W/4]``,
    ``[B, 128, H/8, W/8]``, ``[B, 256, H/16, W/16]``, ``[B, 512, H/32, W/32]``.
    """

    channels = CHANNELS

    def __init__(self, num_images: int = 1, weights: str | None = None) -> None:
        super().__init__()
        self.num_images = num_images
        self.conv1 = GemmWeightGradConv2d(3 * num_images, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.layer1 = nn.Sequential(BasicBlock(64, 64, 1), BasicBlock(64, 64, 1))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128, 1))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256, 1))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512, 1))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        if weights:
            load_imagenet_weights(self, weights)

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        sizes = check_shape("images", images, "B,C,H,W", C=3 * self.num_images)
        if sizes["H"] % ENCODER_STRIDE or sizes["W"] % ENCODER_STRIDE:
            raise ValueError(f"images: expected H, W divisible by {ENCODER_STRIDE}, got {tuple(images.shape)}")
        x = F.relu(self.bn1(self.conv1((images - MEAN) / STD)))
        features = [x]
        x = self.layer1(F.max_pool2d(x, 3, stride=2, padding=1))
        features.append(x)
        for layer in (self.layer2, self.layer3, self.layer4):
            x = layer(x)
            features.append(x)
        return features


def load_imagenet_weights(encoder: ResNetEncoder, path: str | Path) -> None:
    """Load a local ResNet-18 state dict (the ``fc.*`` classifier is ignored).

    Raises:
        DataFormatError: the file is missing or its tensors do not fit a ResNet-18.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "ResNet-18 weights file (model.encoder_weights) not found")
    state = load_plain_torch_file(path, "a ResNet-18 state dict (model.encoder_weights)")
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}
    if "conv1.weight" in state and encoder.num_images > 1:
        state["conv1.weight"] = state["conv1.weight"].repeat(1, encoder.num_images, 1, 1) / encoder.num_images
    try:
        encoder.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise DataFormatError(path, f"expected a ResNet-18 state dict: {exc}") from None
