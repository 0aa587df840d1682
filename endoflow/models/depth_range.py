"""Where a depth map sits in the model's depth range (``model.min_depth`` to ``model.max_depth``, cm): the share
at its ends, where the disparity sigmoid saturates, tells a collapsed depth network from a working one, with or
without ground truth (validation, ``reconstruct``)."""

from __future__ import annotations

import numpy as np
import torch

from endoflow.config import ModelConfig

# The photometric loss has degenerate answers at the ends of the depth range: at its top no step moves the image
# (the identity warp), which explains the frames of a slow camera whose light moves with it well. A network that
# falls there gets almost no gradient back out of the sigmoid's tail (the warp follows the disparity, whose
# derivative vanishes with the sigmoid). Trained without auto-masking (docs/results.md, the mask study), seed 1's
# validation depth had 8 % of its pixels in this band after epoch 1 and all of them after epochs 2-10 (validation Abs
# Rel 0.341 throughout: a constant map); seed 2's climbed to 27-35 % from epoch 4 on. The SimCol3D validation
# frames' exact depth has none there, nor has an untrained network's.
RANGE_END_MARGIN = 0.01  # a pixel within 1 % of min_depth or max_depth counts as at an end
COLLAPSED_SHARE = 0.25  # a depth map with this share of its field of view at the ends has collapsed


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
