"""Wasserstein GAN losses with gradient penalty (Arjovsky et al. 2017; Gulrajani et al. 2017).

The critic outputs unbounded scores, higher for real samples. Both losses are minimised: the critic
minimises ``critic_loss + gradient_penalty``, the generator ``generator_loss``.
"""

from __future__ import annotations

from typing import Callable

import torch

from endoflow.shapes import check_same_shape


def critic_loss(real_scores: torch.Tensor, fake_scores: torch.Tensor) -> torch.Tensor:
    """``mean(D(fake)) - mean(D(real))``: the negated Wasserstein estimate the critic minimises."""
    return fake_scores.mean() - real_scores.mean()


def generator_loss(fake_scores: torch.Tensor) -> torch.Tensor:
    """``-mean(D(fake))``."""
    return -fake_scores.mean()


def gradient_penalty(
    critic: Callable[[torch.Tensor], torch.Tensor], real: torch.Tensor, fake: torch.Tensor, gamma: float
) -> torch.Tensor:
    """``gamma * E[(||grad_x D(x)||_2 - 1)^2]`` at random interpolates ``x = a real + (1 - a) fake``.

    One ``a ~ U(0, 1)`` per sample; ``fake`` is detached (the penalty trains the critic only). The gradient
    is taken with ``create_graph=True`` so the penalty itself back-propagates into the critic's weights.
    """
    check_same_shape("real", real, "fake", fake)
    alpha = torch.rand((real.shape[0],) + (1,) * (real.ndim - 1), device=real.device, dtype=real.dtype)
    interpolates = (alpha * real.detach() + (1 - alpha) * fake.detach()).requires_grad_(True)
    scores = critic(interpolates)
    (gradients,) = torch.autograd.grad(scores.sum(), interpolates, create_graph=True)
    norms = gradients.flatten(1).norm(dim=1)
    return gamma * (norms - 1).square().mean()
