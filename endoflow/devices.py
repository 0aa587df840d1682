"""Where a stage computes and in what precision: the one home of both choices.

A device key's value (``auto``, ``cpu``, ``cuda``, ``cuda:N``) as a torch device, failing with the key's name;
a precision key's value as bf16 autocast or float32; the memory layout of the networks (:func:`wants_channels_last`);
torch's CPU thread count;
8-bit images to float in [0, 1] (:func:`unit_float_images`); whether a step runs compiled (:func:`compiled`). See
docs/method.md, "Devices and precision".
"""

from __future__ import annotations

from typing import Callable, TypeVar

import torch
from torch import nn

from endoflow.config import DEVICE_NAME, Compile, ConfigError, Precision

Step = TypeVar("Step", bound=Callable)

# The first CUDA compute capability with native bf16 arithmetic (Ampere); older GPUs emulate it slowly.
NATIVE_BF16_CAPABILITY = (8, 0)
# The smallest frame side (px) whose convolutions run channels-last on a CPU. Measured on 2 cores (docs/benchmarks.md,
# docs/method.md): float32 depth inference 1.6x faster from 128 px up, the paper preset's 480 px step 1.43x; at 64 px
# the default step is 5 % slower and inference the same, so the default run keeps its contiguous layout. In bf16
# (oneDNN's native bf16 convolutions) depth inference 1.5x at 480 px and 1.4x at 256 px, the 480 px step 1.17x.
CPU_CHANNELS_LAST_MIN_PX = 128


def use_cpu_threads(count: int) -> None:
    """torch computes on ``count`` CPU threads in this process from now on (``threads`` in params): a sum split
    over threads adds in another order with another count, so a fixed count, rather than this machine's number
    of cores, gives the same numbers on any machine."""
    torch.set_num_threads(count)


def resolve_device(name: str, key: str) -> torch.device:
    """The torch device that the value ``name`` of parameter ``key`` asks for (see the module docstring).

    Raises:
        ConfigError: naming ``key`` when ``name`` is no device name, or asks for a device this machine lacks.
    """
    if DEVICE_NAME.fullmatch(name) is None:
        raise ConfigError(f"{key} must be auto, cpu, cuda or cuda:N, got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            raise ConfigError(f"{key} is {name!r} but torch sees {count} CUDA device(s) on this machine; "
                              f"set {key} to auto or cpu")
    return device


def compute_dtype(device: torch.device, precision: Precision) -> torch.dtype:
    """``torch.bfloat16`` when ``precision`` means bf16 autocast on ``device``, else ``torch.float32``."""
    if precision == "bf16":
        return torch.bfloat16
    if precision == "auto" and device.type == "cuda":
        native = torch.cuda.get_device_capability(device) >= NATIVE_BF16_CAPABILITY
        return torch.bfloat16 if native else torch.float32
    return torch.float32


def autocast(device: torch.device, precision: Precision) -> torch.autocast:
    """The autocast context for ``precision`` on ``device``: bf16 autocast, or autocast off (float32)."""
    dtype = compute_dtype(device, precision)
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16)


def wants_channels_last(device: torch.device, precision: Precision, size: int) -> bool:
    """Whether the networks compute channels-last for frames whose smaller side is ``size`` px: bf16 convolutions on
    CUDA (tensor cores), and every convolution on a CPU from :data:`CPU_CHANNELS_LAST_MIN_PX` up (oneDNN)."""
    if device.type == "cuda":
        return compute_dtype(device, precision) == torch.bfloat16
    return size >= CPU_CHANNELS_LAST_MIN_PX


def to_compute_layout(module: nn.Module, device: torch.device, precision: Precision, size: int) -> nn.Module:
    """``module`` on ``device``, its 4-d weights channels-last where :func:`wants_channels_last` says so for frames
    of ``size`` px."""
    module = module.to(device)
    if wants_channels_last(device, precision, size):
        module = module.to(memory_format=torch.channels_last)
    return module


def unit_float_images(images: torch.Tensor) -> torch.Tensor:
    """8-bit colour (``uint8``, 0..255) as float32 in [0, 1]; float images are returned as they are."""
    if images.dtype == torch.uint8:
        return images.float() / 255.0
    if not images.is_floating_point():
        raise TypeError(f"images must be uint8 (8-bit colour) or floating point, got {images.dtype}")
    return images


def images_to_device(images: torch.Tensor, device: torch.device, precision: Precision) -> torch.Tensor:
    """Images ``[B, C, H, W]`` (8-bit or float) on ``device`` as float in [0, 1] (:func:`unit_float_images`, after
    the copy), channels-last where the weights are (:func:`to_compute_layout` for frames of their size)."""
    images = unit_float_images(images.to(device, non_blocking=True))
    if wants_channels_last(device, precision, min(images.shape[-2:])):
        images = images.contiguous(memory_format=torch.channels_last)
    return images


def batch_to_device(batch: dict, device: torch.device, precision: Precision) -> dict:
    """A loader batch on ``device``: its images as :func:`images_to_device` puts them, other tensors moved,
    everything else (keys, metadata) as it is."""
    return {key: images_to_device(value, device, precision) if _is_image(value)
            else value.to(device, non_blocking=True) if isinstance(value, torch.Tensor) else value
            for key, value in batch.items()}


def _is_image(value: object) -> bool:
    # masks (the field of view) are [B, 1, H, W] too, but bool: moved as they are
    return isinstance(value, torch.Tensor) and value.dim() == 4 and value.dtype != torch.bool


def compiles(device: torch.device, setting: Compile) -> bool:
    """Whether ``setting`` compiles a step on ``device``: ``auto`` does on CUDA only. On a CPU, inductor's C++
    backend needs a compiler and minutes of warm-up on 2 cores, which a short run never earns back.

    Raises:
        ValueError: for any other setting (a string such as ``"on"`` would otherwise run eager unnoticed).
    """
    if not (isinstance(setting, bool) or setting == "auto"):
        raise ValueError(f"compile setting {setting!r}: expected True, False or 'auto'")
    return setting is True or (setting == "auto" and device.type == "cuda")


def compiled(step: Step, device: torch.device, setting: Compile) -> Step:
    """``step`` through ``torch.compile`` where :func:`compiles` says so, else ``step`` itself.

    Random draws inside the step (the pose VAE's samples, the bank's noise) come from torch's own generator as in
    eager mode (inductor's ``fallback_random``), so a seed gives the same draws compiled or not and a resumed run
    continues the same sequence. The compiler runs on the first call (the backward's on the first backward); where
    it fails, its error says so, and ``train.compile: false`` runs the step eager.

    Raises:
        ValueError: for a ``setting`` other than True, False and ``"auto"`` (:func:`compiles`).
    """
    if not compiles(device, setting):
        return step
    return torch.compile(step, options={"fallback_random": True})  # type: ignore[return-value]
