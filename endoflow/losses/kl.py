"""KL divergence of a diagonal Gaussian posterior to the standard normal prior (the VAE pose constraint)."""

from __future__ import annotations

import torch


def kl_standard_normal(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """``KL(N(mean, diag(exp(logvar))) || N(0, I))`` in closed form, one value per batch element ``[B]``.

    ``0.5 * sum(exp(logvar) + mean^2 - 1 - logvar)`` over every dimension but the first (for pose
    vectors ``[B, 6]``: over the 6 parameters).
    """
    if mean.shape != logvar.shape or mean.ndim < 2:
        raise ValueError(f"mean, logvar: expected two [B, D...] tensors of one shape, "
                         f"got {tuple(mean.shape)}, {tuple(logvar.shape)}")
    per_dim = logvar.exp() + mean.square() - 1 - logvar
    return 0.5 * per_dim.flatten(1).sum(dim=1)
