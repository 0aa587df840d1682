"""The optimiser and learning-rate schedule of training and of ``endoflow adapt`` (no Ray: adapting runs in one
process)."""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from endoflow.config import TrainConfig


def make_optimizer(parameters: list[nn.Parameter], cfg: TrainConfig, intrinsics: Optional[list[nn.Parameter]] = None
                   ) -> torch.optim.Optimizer:
    """Adam with ``train.weight_decay`` decoupled (``adamw``) or added to the gradient (``adam``); ``intrinsics``,
    the learned cameras' corrections, in a group of their own at ``train.intrinsics_lr`` without decay (which
    would pull them back to the assumed K). torch's fused kernel: the same update to rounding, and on 2 CPU cores
    the default model's step over its 27.7 M parameters took 28 ms against 88 ms for the per-parameter loop."""
    optimizer = torch.optim.AdamW if cfg.optimizer == "adamw" else torch.optim.Adam
    groups = [{"params": parameters}]
    if intrinsics:
        groups.append({"params": intrinsics, "lr": cfg.intrinsics_lr, "weight_decay": 0.0})
    return optimizer(groups, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)


def make_scheduler(optimizer: torch.optim.Optimizer, cfg: TrainConfig) -> torch.optim.lr_scheduler.LRScheduler:
    """Per-epoch learning-rate schedule from ``train.schedule``."""
    if cfg.schedule == "step":
        return torch.optim.lr_scheduler.StepLR(optimizer, step_size=cfg.step_epochs, gamma=cfg.gamma)
    if cfg.schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(cfg.epochs, 1))
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
