"""``train.optimizer``: weight decay decoupled from the gradient (adamw) or added to it (adam); the schedule of a run
resumed with more epochs."""

from __future__ import annotations

import math

import pytest
import torch

from endoflow.config import TrainConfig
from endoflow.training.optimization import make_optimizer, make_scheduler, restore_scheduler


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


def rates_by_epoch(epochs: int, resumed_after: int | None = None, saved_epochs: int | None = None) -> list[float]:
    """The rate of each epoch of a run of ``epochs`` epochs at the cosine schedule (two groups: the network's and the
    learned intrinsics'); with ``resumed_after``, the first epochs ran in a run of ``saved_epochs`` epochs, whose
    optimiser and schedule the rest resumes from."""
    def fresh(cfg: TrainConfig) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
        optimizer = make_optimizer([torch.nn.Parameter(torch.ones(1))], cfg, [torch.nn.Parameter(torch.ones(1))])
        return optimizer, make_scheduler(optimizer, cfg)

    def run(optimizer, scheduler, count: int) -> list[float]:
        rates = []
        for _ in range(count):
            rates.append(optimizer.param_groups[0]["lr"])
            optimizer.step()
            scheduler.step()
        return rates

    cfg = TrainConfig(epochs=epochs, schedule="cosine")
    if resumed_after is None:
        return run(*fresh(cfg), epochs)
    first_optimizer, first_scheduler = fresh(TrainConfig(epochs=saved_epochs, schedule="cosine"))
    first = run(first_optimizer, first_scheduler, resumed_after)
    optimizer, scheduler = fresh(cfg)
    optimizer.load_state_dict(first_optimizer.state_dict())
    restore_scheduler(scheduler, first_scheduler.state_dict(), optimizer)
    assert optimizer.param_groups[1]["lr"] == pytest.approx(
        cfg.intrinsics_lr * (1 + math.cos(math.pi * resumed_after / epochs)) / 2)
    return first + run(optimizer, scheduler, epochs - resumed_after)


@pytest.mark.parametrize("saved_epochs, resumed_after", [(3, 3), (4, 2)])
def test_a_cosine_run_resumed_with_more_epochs_follows_the_longer_schedule(saved_epochs: int, resumed_after: int):
    # a 3-epoch run ends at rate 0 and a 4-epoch one stopped after 2 at half the rate; given 10 epochs, the epochs
    # left take the 10-epoch schedule's rates
    ten = rates_by_epoch(10)
    resumed = rates_by_epoch(10, resumed_after=resumed_after, saved_epochs=saved_epochs)
    assert resumed[resumed_after:] == pytest.approx(ten[resumed_after:], rel=1e-9)
    assert min(resumed[resumed_after:]) > 0


def test_a_cosine_run_cut_below_its_progress_resumes_at_the_end_of_the_shorter_schedule():
    # 6 of 10 epochs done, then 5 asked for: nothing is left to train, and the rate is the schedule's end
    first_cfg, cfg = TrainConfig(epochs=10, schedule="cosine"), TrainConfig(epochs=5, schedule="cosine")
    optimizer = make_optimizer([torch.nn.Parameter(torch.ones(1))], first_cfg)
    scheduler = make_scheduler(optimizer, first_cfg)
    for _ in range(6):
        optimizer.step()
        scheduler.step()
    resumed_optimizer = make_optimizer([torch.nn.Parameter(torch.ones(1))], cfg)
    resumed_optimizer.load_state_dict(optimizer.state_dict())
    restore_scheduler(make_scheduler(resumed_optimizer, cfg), scheduler.state_dict(), resumed_optimizer)
    assert resumed_optimizer.param_groups[0]["lr"] == pytest.approx(0.0, abs=1e-15)


def test_a_run_resumed_at_its_own_length_keeps_its_schedule_exactly():
    assert rates_by_epoch(10, resumed_after=4, saved_epochs=10) == rates_by_epoch(10)
