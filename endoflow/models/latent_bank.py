"""The generative latent bank: a StyleGAN-like generator of one-channel depth maps, and its file.

Two modes share one set of weights: generating depth maps for pretraining (:meth:`LatentBankGenerator.forward`)
and, frozen, giving DepthNet the feature map of every block (:meth:`LatentBankGenerator.bank_features`);
``models/latent_bank.pt`` holds its spec and weights (:func:`load_generator`). See docs/method.md, "Generative
latent bank" and "DepthNet".
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from endoflow.errors import DataFormatError
from endoflow.models.edge_padding import edge_pad
from endoflow.io import load_plain_torch_file
from endoflow.shapes import check_shape

LATENT_BANK_FORMAT = "endoflow.latent_bank/2"  # 2: the synthesis convolutions record their init_scale
_RERUN = "(re)run the pretrain_latent_bank stage to write it"


@dataclass(frozen=True)
class GeneratorSpec:
    """Architecture of a :class:`LatentBankGenerator`; stored beside its weights in ``latent_bank.pt``."""

    resolution: int
    start_resolution: int
    latent_dim: int
    style_dim: int
    mapping_layers: int
    channel_base: int
    channel_max: int
    # Initial scale of the synthesis convolutions, relative to PyTorch's default (see InitScaled).
    conv_init_scale: float

    def __post_init__(self) -> None:
        for name in ("resolution", "start_resolution"):
            value = getattr(self, name)
            if value < 4 or value & (value - 1):
                raise ValueError(f"{name} must be a power of two >= 4, got {value}")
        if self.start_resolution > self.resolution:
            raise ValueError(
                f"start_resolution {self.start_resolution} exceeds resolution {self.resolution}"
            )

    @property
    def resolutions(self) -> list[int]:
        """Output resolution of each block, coarsest first."""
        count = int(math.log2(self.resolution // self.start_resolution)) + 1
        return [self.start_resolution * 2**i for i in range(count)]

    def channels(self, resolution: int) -> int:
        """Feature channels at ``resolution`` (ProGAN's rule: base / resolution, capped)."""
        return max(1, min(self.channel_base // resolution, self.channel_max))

    def to_dict(self) -> dict[str, int | float]:
        return asdict(self)


def pixel_norm(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Normalise each vector to unit root-mean-square over dimension 1."""
    return x * torch.rsqrt(x.pow(2).mean(dim=1, keepdim=True) + eps)


class MappingNetwork(nn.Module):
    """MLP latent ``z [B, latent_dim]`` -> style ``w [B, style_dim]``."""

    def __init__(self, latent_dim: int, style_dim: int, layers: int) -> None:
        super().__init__()
        blocks: list[nn.Module] = []
        width = latent_dim
        for _ in range(layers):
            blocks += [nn.Linear(width, style_dim), nn.LeakyReLU(0.2)]
            width = style_dim
        self.net = nn.Sequential(*blocks)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(pixel_norm(z))


class AdaIN(nn.Module):
    """Adaptive instance normalisation: ``(1 + gamma(s)) * instance_norm(x) + beta(s)``.

    The style ``s`` is a vector ``[B, S]`` (one style per image, as in StyleGAN) or a map ``[B, S, H, W]``
    on ``x``'s grid (one style per pixel); the affine map from style to ``(gamma, beta)`` is the same
    linear layer in both cases. The generator's own blocks start with a random affine map (so different
    latents give different maps from the first step); ``zero_init`` starts at the identity modulation, so
    a block added to a pretrained cascade first passes normalised features through.
    """

    def __init__(self, channels: int, style_dim: int, zero_init: bool = False) -> None:
        super().__init__()
        self.channels = channels
        self.affine = nn.Linear(style_dim, 2 * channels)
        nn.init.zeros_(self.affine.bias)
        if zero_init:
            nn.init.zeros_(self.affine.weight)

    def forward(self, x: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        if style.ndim == 2:
            params = self.affine(style)[:, :, None, None]
        elif style.ndim == 4:
            if style.shape[-2:] != x.shape[-2:]:
                raise ValueError(f"style map grid {tuple(style.shape[-2:])} != features {tuple(x.shape[-2:])}")
            params = F.conv2d(style, self.affine.weight[:, :, None, None], self.affine.bias)
        else:
            raise ValueError(f"style: expected [B, S] or [B, S, H, W], got {tuple(style.shape)}")
        gamma, beta = params.chunk(2, dim=1)
        return (1 + gamma) * instance_norm(x) + beta


def instance_norm(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Per-sample, per-channel normalisation over the grid; a 1x1 map (a 32-pixel input's coarsest
    level) normalises to zero instead of failing as ``nn.InstanceNorm2d`` does in training."""
    mean = x.mean(dim=(2, 3), keepdim=True)
    var = x.var(dim=(2, 3), keepdim=True, unbiased=False)
    return (x - mean) * torch.rsqrt(var + eps)


class NoiseInjection(nn.Module):
    """Adds per-pixel Gaussian noise ``[B, 1, H, W]`` scaled by a learned per-channel strength (init 0)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.strength = nn.Parameter(torch.zeros(1, channels, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        noise = torch.randn(x.shape[0], 1, *x.shape[-2:], device=x.device, dtype=x.dtype)
        return x + self.strength * noise


def blur(x: torch.Tensor) -> torch.Tensor:
    """Fixed 3x3 binomial low-pass filter per channel. After a stride-2 transposed convolution it removes
    the checkerboard pattern the upsampling leaves (as StyleGAN filters its upsampling)."""
    kernel = torch.tensor([1.0, 2.0, 1.0], device=x.device, dtype=x.dtype)
    kernel = (kernel[:, None] * kernel[None, :] / 16).expand(x.shape[1], 1, 3, 3)
    return F.conv2d(edge_pad(x), kernel, groups=x.shape[1])


class InitScaled:
    """Mixin for ``nn.Conv2d`` and ``nn.ConvTranspose2d``: weight and bias start at ``init_scale`` times
    PyTorch's default initialisation (the same random draw, multiplied), and the scale is a persistent buffer,
    so a state dict shows how the layer was built.

    Why a scale: the generator's synthesis convolutions reach an instance normalisation (AdaIN) only through
    scale-free steps (blur, leaky ReLU, noise whose strength starts at 0), so their weights' size does not
    change what a fresh generator computes, up to the normalisation's epsilon; only their direction does.
    Adam moves every weight by about ``lr`` per step whatever its size, so such a layer turns by about
    ``lr / |w|`` per step. PyTorch's default (``|w| ~ 1 / sqrt(fan_in)``) gives the few-channel
    high-resolution blocks the largest weights, and at the paper's fixed lr they barely turn in a short run;
    ``init_scale`` < 1 makes the layer turn ``1 / init_scale`` times faster, the effect StyleGAN gets from its
    equalised learning rate.
    """

    weight: nn.Parameter
    bias: nn.Parameter | None

    def __init__(self, *args: Any, init_scale: float = 1.0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.register_buffer("init_scale", torch.tensor(float(init_scale)))
        self._scale_parameters(init_scale)

    def reset_parameters(self) -> None:
        super().reset_parameters()  # type: ignore[misc]
        # The parent constructor draws its initialisation before __init__ has registered the scale;
        # __init__ scales that first draw itself.
        if hasattr(self, "init_scale"):
            self._scale_parameters(self.init_scale.item())

    @torch.no_grad()
    def _scale_parameters(self, scale: float) -> None:
        self.weight.mul_(scale)
        if self.bias is not None:
            self.bias.mul_(scale)


class InitScaledConv2d(InitScaled, nn.Conv2d):
    """``nn.Conv2d`` initialised at ``init_scale`` times PyTorch's default (see :class:`InitScaled`)."""


class InitScaledConvTranspose2d(InitScaled, nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` initialised at ``init_scale`` times PyTorch's default (see :class:`InitScaled`)."""


class SynthesisBlock(nn.Module):
    """One resolution: (transposed-conv upsampling + blur, or nothing) -> noise -> AdaIN -> conv -> noise -> AdaIN.

    The two AdaIN slots are :attr:`adains`; in latent-bank mode the caller passes its own modules instead.
    Both convolutions start at ``conv_init_scale`` times PyTorch's default scale (:class:`InitScaled`).
    """

    def __init__(
        self, in_channels: int, out_channels: int, style_dim: int, upsample: bool, conv_init_scale: float
    ) -> None:
        super().__init__()
        self.up = (
            InitScaledConvTranspose2d(in_channels, out_channels, 4, stride=2, padding=1, init_scale=conv_init_scale)
            if upsample
            else None
        )
        self.conv = InitScaledConv2d(out_channels, out_channels, 3, padding=1, init_scale=conv_init_scale)
        self.noises = nn.ModuleList([NoiseInjection(out_channels), NoiseInjection(out_channels)])
        self.adains = nn.ModuleList([AdaIN(out_channels, style_dim), AdaIN(out_channels, style_dim)])
        self.out_channels = out_channels

    def forward(
        self, x: torch.Tensor, style: torch.Tensor, adains: Sequence[nn.Module] | None = None, noise: bool = True
    ) -> torch.Tensor:
        adains = self.adains if adains is None else adains
        if self.up is not None:
            x = F.leaky_relu(blur(self.up(x)), 0.2)
        x = adains[0](self.noises[0](x) if noise else x, style)
        x = F.leaky_relu(self.conv(x), 0.2)
        return adains[1](self.noises[1](x) if noise else x, style)


class LatentBankGenerator(nn.Module):
    """StyleGAN-like depth generator; see the module docstring for its two modes."""

    def __init__(self, spec: GeneratorSpec) -> None:
        super().__init__()
        self.spec = spec
        res = self.spec.resolutions
        self.mapping = MappingNetwork(self.spec.latent_dim, self.spec.style_dim, self.spec.mapping_layers)
        self.const = nn.Parameter(torch.randn(1, self.spec.channels(res[0]), res[0], res[0]))
        blocks, to_depth = [], []
        for i, r in enumerate(res):
            c_in = self.spec.channels(res[i - 1]) if i else self.spec.channels(r)
            blocks.append(
                SynthesisBlock(c_in, self.spec.channels(r), self.spec.style_dim, i > 0, self.spec.conv_init_scale)
            )
            to_depth.append(nn.Conv2d(self.spec.channels(r), 1, 1))
        self.blocks = nn.ModuleList(blocks)
        self.to_depth = nn.ModuleList(to_depth)

    @property
    def block_channels(self) -> list[int]:
        """Feature channels of each block's output, coarsest first."""
        return [b.out_channels for b in self.blocks]

    def forward(self, z: torch.Tensor, resolution: int | None = None, alpha: float = 1.0) -> torch.Tensor:
        """Generate depth maps ``[B, 1, r, r]`` from latents ``z [B, latent_dim]`` at ``resolution`` r.

        ``alpha`` in [0, 1] fades the newest block in: the output is ``alpha * block_r`` plus
        ``(1 - alpha) *`` the nearest-upsampled output of the previous resolution.
        """
        resolution = resolution or self.spec.resolution
        if resolution not in self.spec.resolutions:
            raise ValueError(f"resolution {resolution} not in {self.spec.resolutions}")
        check_shape("z", z, "B,L", L=self.spec.latent_dim)
        w = self.mapping(z)
        x = self.const.expand(z.shape[0], -1, -1, -1)
        last = self.spec.resolutions.index(resolution)
        previous = x
        for i in range(last + 1):
            previous = x
            x = self.blocks[i](x, w)
        out = self.to_depth[last](x)
        if last > 0 and alpha < 1.0:
            coarse = F.interpolate(self.to_depth[last - 1](previous), scale_factor=2, mode="nearest")
            out = alpha * out + (1 - alpha) * coarse
        return out

    def bank_features(
        self, styles: Sequence[torch.Tensor], adains: Sequence[Sequence[nn.Module]], noise: bool = False
    ) -> list[torch.Tensor]:
        """Latent-bank mode: the cascade's feature maps, driven by external spatial styles.

        Args:
            styles: one style map per block used, coarsest first: ``styles[k]`` is ``[B, style_dim, h*2^k,
                w*2^k]`` (at most ``len(self.blocks)`` maps).
            adains: ``adains[k]`` are the two AdaIN modules (caller-owned, e.g. trainable) for block k.
            noise: inject the learned per-pixel noise (stochastic) or not (deterministic).

        Returns:
            ``[B, block_channels[k], h*2^k, w*2^k]`` for each block k. Gradients flow to ``styles`` and
            ``adains``; the generator's own weights are left as they are (freeze them with
            ``requires_grad_(False)``).
        """
        if not 1 <= len(styles) <= len(self.blocks) or len(adains) != len(styles):
            raise ValueError(
                f"expected 1..{len(self.blocks)} style maps with one AdaIN pair each, "
                f"got {len(styles)} styles and {len(adains)} pairs"
            )
        h, w = styles[0].shape[-2:]
        x = F.interpolate(self.const, size=(h, w), mode="bilinear", align_corners=False)
        x = x.expand(styles[0].shape[0], -1, -1, -1)
        features = []
        for k, (style, pair) in enumerate(zip(styles, adains)):
            expected = (h * 2**k, w * 2**k)
            check_shape(f"styles[{k}]", style, "B,S,H,W", S=self.spec.style_dim, H=expected[0], W=expected[1])
            x = self.blocks[k](x, style, adains=pair, noise=noise)
            features.append(x)
        return features


def generator_payload(generator: LatentBankGenerator, extra: dict | None = None) -> dict:
    """The dict written to ``latent_bank.pt``: tensors and plain values only (``weights_only`` loadable)."""
    return {
        "format": LATENT_BANK_FORMAT,
        "spec": generator.spec.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in generator.state_dict().items()},
        **(extra or {}),
    }


def load_generator(path: str | Path) -> LatentBankGenerator:
    """Rebuild the generator saved by :func:`endoflow.training.pretrain.pretrain_latent_bank`, on the CPU.

    Only tensors and plain data are unpickled (``weights_only=True``). Raises ``FileNotFoundError`` for a
    missing file and :class:`~endoflow.errors.DataFormatError` for one that is truncated, corrupt, holds
    other objects, or is not a latent bank of this format; both messages name the file.
    """
    payload = _read_payload(Path(path))
    generator = LatentBankGenerator(_payload_spec(path, payload))
    state_dict = payload.get("state_dict")
    if not isinstance(state_dict, dict):
        raise DataFormatError(path, f"no 'state_dict' in the latent bank file; {_RERUN}")
    try:
        generator.load_state_dict(state_dict)
    except RuntimeError as error:  # missing, unexpected or misshapen tensors
        problems = " ".join(str(error).split())[:300]
        raise DataFormatError(path, f"weights do not fit the stored architecture ({problems}); {_RERUN}") from error
    return generator


def check_latent_bank_file(path: str | Path) -> None:
    """Fail fast, before training starts, on a latent bank file :func:`load_generator` would reject.

    It loads the file on CPU and rebuilds the generator (the default bank is a few MB; the paper preset's,
    320 MB, takes about a second of CPU), so every error :func:`load_generator` can raise is raised here, with
    the file named.
    """
    load_generator(path)


def _read_payload(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: latent bank file not found; {_RERUN}")
    payload = load_plain_torch_file(path, f"a latent bank file written by pretrain_latent_bank; {_RERUN}")
    if not isinstance(payload, dict) or payload.get("format") != LATENT_BANK_FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise DataFormatError(
            path, f"expected a latent bank file of format {LATENT_BANK_FORMAT!r} written by pretrain_latent_bank, "
                  f"found {found!r}; {_RERUN}"
        )
    return payload


def _payload_spec(path: str | Path, payload: dict) -> GeneratorSpec:
    spec = payload.get("spec")
    expected = {f.name for f in fields(GeneratorSpec)}
    if not isinstance(spec, dict) or set(spec) != expected:
        found = sorted(spec) if isinstance(spec, dict) else type(spec).__name__
        raise DataFormatError(path, f"'spec' must have the keys {sorted(expected)}, found {found}; {_RERUN}")
    try:
        return GeneratorSpec(**spec)
    except (TypeError, ValueError) as error:
        raise DataFormatError(path, f"invalid generator spec: {error}") from error
