"""Time one training step of the full model against the Monodepth2-equivalent ablation, in the same run.

    python benchmarks/bench_train_step.py [--params params.yaml] [--size S] [--batch B] [--threads T]
                                          [--repeats 5] [--device cpu|cuda] [--bf16]

A step is ``training_step_losses`` forward, backward and training's optimiser step (``make_optimizer``) over the
trainable parameters.
"full" is ``params.model`` (latent bank and pose VAE as configured, default both on); "plain" is the same
with ``model.latent_bank=false, model.pose_vae=false``. Defaults: ``data.size`` and ``train.batch_size``
from the params. Runs alternate between the two models so that load from other processes hits both alike;
the median over the repeats is reported with the ratio full / plain (target: at most 1.5) and the
parameter counts. On a GPU: ``--device cuda --size 480 --batch 12 --bf16`` (bf16 autocast).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from endoflow.config import Params, load_params
from endoflow.models.endoflow_model import EndoflowModel, build_model
from endoflow.training.objective import training_step_losses
from endoflow.training.optimization import make_optimizer


def make_batch(batch: int, size: int, device: torch.device) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    K = torch.tensor([[0.5 * size, 0, size / 2], [0, 0.5 * size, size / 2], [0, 0, 1.0]])
    images = {k: torch.rand(batch, 3, size, size, generator=generator).to(device) for k in ("prev", "cur", "next")}
    return {**images, "K": K.expand(batch, 3, 3).contiguous().to(device)}


def make_step(model: EndoflowModel, params: Params, batch: dict, device: torch.device, bf16: bool):
    optimiser = make_optimizer([p for p in model.parameters() if p.requires_grad], params.train)

    def step() -> None:
        optimiser.zero_grad(set_to_none=True)
        with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=bf16):
            losses = training_step_losses(model, batch, params.loss)
        losses["total"].backward()
        optimiser.step()
        if device.type == "cuda":
            torch.cuda.synchronize()

    return step


def count(model: EndoflowModel) -> tuple[int, int]:
    params = list(model.parameters())
    return sum(p.numel() for p in params if p.requires_grad), sum(p.numel() for p in params if not p.requires_grad)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--size", type=int, default=None, help="square input size (default: data.size)")
    parser.add_argument("--batch", type=int, default=None, help="batch size (default: train.batch_size)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--bf16", action="store_true", help="bf16 autocast")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    params = load_params(args.params) if Path(args.params).is_file() else Params()
    size, batch_size = args.size or params.data.size, args.batch or params.train.batch_size
    device = torch.device(args.device)
    plain_model = params.model.replace(latent_bank=False, pose_vae=False)
    plain_params = params.replace(model=plain_model)
    batch = make_batch(batch_size, size, device)
    models = {"full": build_model(params, None), "plain": build_model(plain_params, None)}
    steps = {}
    for name, model in models.items():
        model.to(device).train()
        steps[name] = make_step(model, params if name == "full" else plain_params, batch, device, args.bf16)
        steps[name]()  # warm-up: allocations, autotuning
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.repeats):
        for name, step in steps.items():
            started = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - started)
    print(f"device {device}, size {size}x{size}, batch {batch_size}, bf16 {args.bf16}, "
          f"threads {torch.get_num_threads()}, repeats {args.repeats}")
    medians = {name: statistics.median(values) for name, values in times.items()}
    for name, model in models.items():
        trainable, frozen = count(model)
        print(f"{name:>5}: {medians[name] * 1000:9.1f} ms/step   trainable {trainable:,}   frozen {frozen:,}")
    print(f"ratio full / plain: {medians['full'] / medians['plain']:.3f} (target <= 1.5)")


if __name__ == "__main__":
    main()
