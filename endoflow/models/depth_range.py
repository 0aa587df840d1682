"""Where a depth map sits in the model's depth range (``model.min_depth`` to ``model.max_depth``, cm): the share
at its ends, where the disparity sigmoid saturates, tells a collapsed depth network from a working one, with or
without ground truth (validation, ``reconstruct``)."""

from __future__ import annotations

import numpy as np
import torch

from endoflow.config import ModelConfig

# The photometric loss has degenerate answers at the ends of the depth range: at its top no step moves the image
# (the identity warp), which explains the frames of a slow camera whose light moves with it well. A network that
# falls there gets no gradient back out of the sigmoid's tail: trained without auto-masking, the mask study's
# seed 1 stayed at one validation Abs Rel from its second epoch to its tenth, every pixel at max_depth, and seed 2
# put 83 % of the real clip's pixels there (docs/results.md).
RANGE_END_MARGIN = 0.01  # a pixel within 1 % of min_depth or max_depth counts as at an end
COLLAPSED_SHARE = 0.5  # a depth map with this share of its field of view at the ends has collapsed


def at_depth_range_ends(depth_cm: torch.Tensor | np.ndarray, cfg: ModelConfig) -> torch.Tensor | np.ndarray:
    """Where ``depth_cm`` (a tensor or an array, any shape) lies within :data:`RANGE_END_MARGIN` of ``cfg``'s
    ``min_depth`` or ``max_depth``: the sigmoid's saturated tails, where the depth network has no gradient left."""
    return (depth_cm >= (1 - RANGE_END_MARGIN) * cfg.max_depth) | (depth_cm <= (1 + RANGE_END_MARGIN) * cfg.min_depth)


def collapsed_depth_warning(share: float, cfg: ModelConfig, where: str) -> str | None:
    """A warning when ``share`` (of the pixels in view, :func:`at_depth_range_ends`) reaches
    :data:`COLLAPSED_SHARE`, naming ``where`` it was seen; else None."""
    if share < COLLAPSED_SHARE:
        return None
    return (f"{share:.0%} of the depth {where} sits at an end of its range ({cfg.min_depth:g}-{cfg.max_depth:g} cm, "
            f"model.min_depth and model.max_depth): the depth network has collapsed to the photometric loss's "
            f"degenerate answer, and a path or surface from it says nothing about the scene (training with "
            f"loss.automask on, the default, guards against it)")
