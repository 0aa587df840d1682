"""DepthNet: ResNet-18 encoder, optional frozen generative latent bank, Monodepth2-style disparity decoder.

With ``model.latent_bank`` the encoder's features drive the frozen generator through per-pixel style maps and
new AdaIN blocks, and the decoder reads both; without it, the same encoder and decoder (the paper's ablation).
See docs/method.md, "DepthNet".
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from endoflow.config import ModelConfig
from endoflow.models.edge_padding import EdgePaddedConv2d
from endoflow.models.latent_bank import AdaIN, LatentBankGenerator
from endoflow.models.resnet_encoder import ResNetEncoder

DECODER_CHANNELS = (16, 32, 64, 128, 256)
LEVELS = 5


class ConvELU(nn.Module):
    """3x3 convolution with edge padding, then ELU (Monodepth2 pads by reflection, which fails on 1x1 maps)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = EdgePaddedConv2d(in_channels, out_channels, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.elu(self.conv(x))


class BankAdapters(nn.Module):
    """The new trainable layers of latent-bank mode: encoder features -> style maps, and AdaIN pairs."""

    def __init__(self, encoder_channels: tuple[int, ...], generator: LatentBankGenerator) -> None:
        super().__init__()
        self.blocks = min(len(generator.blocks), LEVELS)
        style_dim = generator.spec.style_dim
        levels = [LEVELS - 1 - k for k in range(self.blocks)]  # encoder level of each block, coarsest first
        self.levels = levels
        self.styles = nn.ModuleList(
            [
                # Per-pixel (1x1) layers: the encoder features already carry spatial context, and the
                # fine levels are large grids where a 3x3 head would cost as much as the decoder.
                nn.Sequential(
                    nn.Conv2d(encoder_channels[level], style_dim, 1),
                    nn.LeakyReLU(0.2),
                    nn.Conv2d(style_dim, style_dim, 1),
                )
                for level in levels
            ]
        )
        self.adains = nn.ModuleList(
            [
                nn.ModuleList([AdaIN(c, style_dim, zero_init=True), AdaIN(c, style_dim, zero_init=True)])
                for c in generator.block_channels[: self.blocks]
            ]
        )

    def style_maps(self, features: list[torch.Tensor]) -> list[torch.Tensor]:
        return [head(features[level]) for head, level in zip(self.styles, self.levels)]


class DepthDecoder(nn.Module):
    """Monodepth2's decoder with extra skip channels for the bank features at each level."""

    def __init__(self, encoder_channels: tuple[int, ...], bank_channels: list[int], scales: int) -> None:
        super().__init__()
        self.scales = scales
        skip = [e + b for e, b in zip(encoder_channels, bank_channels)]
        self.upconv0 = nn.ModuleList()
        self.upconv1 = nn.ModuleList()
        for i in range(LEVELS - 1, -1, -1):
            c_in = skip[-1] if i == LEVELS - 1 else DECODER_CHANNELS[i + 1]
            self.upconv0.append(ConvELU(c_in, DECODER_CHANNELS[i]))
            c_in = DECODER_CHANNELS[i] + (skip[i - 1] if i > 0 else 0)
            self.upconv1.append(ConvELU(c_in, DECODER_CHANNELS[i]))
        self.dispconvs = nn.ModuleList(
            [EdgePaddedConv2d(DECODER_CHANNELS[s], 1, 3) for s in range(scales)]
        )

    def forward(self, skips: list[torch.Tensor]) -> list[torch.Tensor]:
        disps: list[torch.Tensor] = [torch.empty(0)] * self.scales
        x = skips[-1]
        for step, i in enumerate(range(LEVELS - 1, -1, -1)):
            x = F.interpolate(self.upconv0[step](x), scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat([x, skips[i - 1]], dim=1)
            x = self.upconv1[step](x)
            if i < self.scales:
                disps[i] = torch.sigmoid(self.dispconvs[i](x))
        return disps


class DepthNet(nn.Module):
    """RGB ``[B, 3, H, W]`` in [0, 1] (H, W divisible by 32) -> ``model_cfg.scales`` sigmoid disparities.

    Output ``s`` is ``[B, 1, H / 2^s, W / 2^s]``. ``generator`` is required when ``model_cfg.latent_bank``;
    it is frozen here (``requires_grad_(False)``) and registered as ``self.bank`` so it moves with the model.
    """

    def __init__(self, model_cfg: ModelConfig, generator: LatentBankGenerator | None) -> None:
        super().__init__()
        if not 1 <= model_cfg.scales <= 4:
            raise ValueError(f"model.scales must be in 1..4, got {model_cfg.scales}")
        if model_cfg.latent_bank and generator is None:
            raise ValueError("model.latent_bank is true but no latent bank generator was given")
        self.bank_noise = model_cfg.bank_noise
        self.encoder = ResNetEncoder(num_images=1, weights=model_cfg.encoder_weights)
        bank_channels = [0] * LEVELS
        self.bank: LatentBankGenerator | None = None
        self.adapters: BankAdapters | None = None
        if model_cfg.latent_bank:
            self.bank = generator.requires_grad_(False)
            self.adapters = BankAdapters(ResNetEncoder.channels, generator)
            for level, c in zip(self.adapters.levels, generator.block_channels):
                bank_channels[level] = c
        self.decoder = DepthDecoder(ResNetEncoder.channels, bank_channels, model_cfg.scales)

    def forward(self, rgb: torch.Tensor) -> list[torch.Tensor]:
        features = self.encoder(rgb)
        skips = list(features)
        if self.bank is not None:
            bank = self.bank_features(features)
            for level, a in zip(self.adapters.levels, bank):
                skips[level] = torch.cat([features[level], a], dim=1)
        return self.decoder(skips)

    def bank_features(self, features: list[torch.Tensor]) -> list[torch.Tensor]:
        """The frozen bank's feature maps ``a``, coarsest first, on the grids of the matching encoder levels."""
        styles = self.adapters.style_maps(features)
        return self.bank.bank_features(styles, self.adapters.adains, noise=self.bank_noise and self.training)
