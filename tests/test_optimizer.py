"""``train.optimizer``: weight decay decoupled from the gradient (adamw) or added to it (adam)."""

from __future__ import annotations


import pytest
import torch

from endoflow.config import TrainConfig
from endoflow.training.optimization import make_optimizer


def weight_after_small_pulls(optimizer_name: str, steps: int = 10) -> float:
    """A weight of 1 whose loss gradient (-1e-6) pulls it up, after ``steps`` of the optimiser."""
    weight = torch.nn.Parameter(torch.ones(1))
    cfg = TrainConfig(optimizer=optimizer_name, lr=1e-2, weight_decay=1e-3)
    optimizer = make_optimizer([weight], cfg)
    for _ in range(steps):
        optimizer.zero_grad()
        (-1e-6 * weight).sum().backward()
        optimizer.step()
    return float(weight.detach())


def test_adamw_follows_a_small_loss_gradient():
    # Adam normalises the step, so a tiny gradient still moves the weight by about lr per step.
    assert weight_after_small_pulls("adamw") == pytest.approx(1 + 10 * 1e-2, abs=2e-3)


def test_adam_with_l2_decay_lets_the_decay_override_a_small_loss_gradient():
    # The decay term (1e-3 * w) dwarfs the loss gradient, and Adam normalises the sum: the weight shrinks.
    assert weight_after_small_pulls("adam") < 1 - 5e-2


def test_the_optimizer_is_the_one_named():
    weight = torch.nn.Parameter(torch.ones(1))
    assert isinstance(make_optimizer([weight], TrainConfig(optimizer="adamw")),
                      torch.optim.AdamW)
    assert type(make_optimizer([weight], TrainConfig(optimizer="adam"))) is torch.optim.Adam


@pytest.mark.parametrize("name", ["adamw", "adam"])
def test_the_fused_optimizer_steps_as_the_per_parameter_loop_does(name: str) -> None:
    torch.manual_seed(0)
    weights = [torch.nn.Parameter(torch.randn(64, 32)), torch.nn.Parameter(torch.randn(7))]
    intrinsics = [torch.nn.Parameter(torch.zeros(4))]
    loop_weights = [torch.nn.Parameter(w.detach().clone()) for w in weights + intrinsics]
    cfg = TrainConfig(optimizer=name, lr=1e-2, weight_decay=1e-2)
    fused = make_optimizer(weights, cfg, intrinsics)
    assert all(group["fused"] for group in fused.param_groups)
    loop = type(fused)([{"params": loop_weights[:2]}, {"params": loop_weights[2:], "lr": cfg.intrinsics_lr,
                                                          "weight_decay": 0.0}],
                       lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=False)
    for _ in range(5):
        gradients = [torch.randn_like(w) for w in weights + intrinsics]
        for w, lw, g in zip(weights + intrinsics, loop_weights, gradients):
            w.grad, lw.grad = g.clone(), g.clone()
        fused.step()
        loop.step()
    for w, lw in zip(weights + intrinsics, loop_weights):
        assert torch.allclose(w, lw, rtol=0, atol=1e-6)
