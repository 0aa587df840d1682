"""KL divergence of a diagonal Gaussian posterior to the standard normal prior (the VAE pose constraint)."""

from __future__ import annotations

import torch

from endoflow.shapes import check_same_shape, check_shape


def kl_standard_normal(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """``KL(N(mean, diag(exp(logvar))) || N(0, I))`` in closed form, one value per batch element ``[B]``.

    ``0.5 * sum(exp(logvar) + mean^2 - 1 - logvar)`` over every dimension but the first (for pose
    vectors ``[B, 6]``: over the 6 parameters).
    """
    check_shape("mean", mean, "B,D,...")
    check_same_shape("mean", mean, "logvar", logvar)
    per_dim = logvar.exp() + mean.square() - 1 - logvar
    return 0.5 * per_dim.flatten(1).sum(dim=1)
