"""The training step of an earlier version of the code against this one, eager and compiled, in one run.

    python benchmarks/bench_step_versions.py --baseline DIR [--preset presets/paper.yaml] [--size 480]
                                             [--batch B] [--device cpu|cuda] [--precision bf16|float32]
                                             [--steps N] [--rounds R] [--threads T] [--no-compile]

``DIR`` holds an earlier ``endoflow`` package (``git archive <commit> endoflow | tar -x -C DIR``). Each variant
runs in its own process: ``before`` (DIR's code, eager), ``after`` (this tree, eager) and ``compiled`` (this tree,
the step through :func:`endoflow.devices.compiled` as training runs it with ``train.compile``). A step is
``training_step_losses`` forward, backward and an optimiser step (``make_optimizer``, as training's), on one
random batch (seed 0) and the preset's model initialised from seed 0 (its latent bank random: the same compute
as a pretrained one). Printed per variant: the median step time over ``--steps`` timed steps after two warm-up
steps (their time, compilation included, printed apart), samples/s, peak memory, and the first step's losses;
then the speed-ups over ``before`` and the largest relative difference of any loss term from ``before``'s (the
same function computed, to rounding). With ``--rounds`` > 1 the variants alternate, round after round, so that
load from other processes hits all alike, and the median of the rounds is taken. Defaults: batch 12 on a GPU, 2 on
a CPU; bf16 on a GPU, float32 on a CPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from code_versions import environment_importing

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("before", "after", "compiled")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="folder holding the earlier endoflow package")
    parser.add_argument("--preset", default="presets/paper.yaml",
                        help="a preset, or 'defaults' for the config schema's (params.yaml holds keys the "
                             "baseline may not know)")
    parser.add_argument("--size", type=int, default=480)
    parser.add_argument("--batch", type=int, default=None, help="default: 12 on a GPU, 2 on a CPU")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precision", choices=("bf16", "float32"), default=None,
                        help="default: bf16 on a GPU, float32 on a CPU")
    parser.add_argument("--steps", type=int, default=None, help="timed steps (default: 20 on a GPU, 3 on a CPU)")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads of each variant")
    parser.add_argument("--no-compile", action="store_true", help="leave the compiled variant out")
    parser.add_argument("--worker", choices=VARIANTS, help=argparse.SUPPRESS)
    return parser.parse_args()


def run_worker(args: argparse.Namespace) -> dict:
    """One variant's figures (this process imports whichever endoflow its PYTHONPATH names)."""
    import time

    import torch

    from endoflow.config import Params, load_params
    from endoflow.devices import autocast, to_compute_layout
    from endoflow.models.endoflow_model import build_model
    from endoflow.training.objective import training_step_losses
    from endoflow.training.optimization import make_optimizer

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    params = Params() if args.preset == "defaults" else load_params(ROOT / args.preset)
    torch.manual_seed(0)
    model = build_model(params, None)
    try:  # this tree: the layout depends on the frames' size; an earlier one's did not
        model = to_compute_layout(model, device, args.precision, args.size)
    except TypeError:
        model = to_compute_layout(model, device, args.precision)
    model = model.train()
    losses_of = training_step_losses
    if args.worker == "compiled":
        from endoflow.devices import compiled

        losses_of = compiled(training_step_losses, device, True)
    batch = random_batch(args.batch, args.size, device)
    optimiser = make_optimizer([p for p in model.parameters() if p.requires_grad], params.train)

    def step() -> dict[str, float]:
        optimiser.zero_grad(set_to_none=True)
        with autocast(device, args.precision):
            losses = losses_of(model, batch, params.loss)
        losses["total"].backward()
        optimiser.step()
        synchronise(device)
        return {key: float(value) for key, value in losses.items()}

    torch.manual_seed(1)  # the pose samples and the bank's noise of the first step, alike in every variant
    started = time.perf_counter()
    first = step()
    step()
    warm_up = time.perf_counter() - started
    reset_peak(device)
    times = []
    for _ in range(args.steps):
        started = time.perf_counter()
        step()
        times.append(time.perf_counter() - started)
    return {"median_s": statistics.median(times), "warm_up_s": warm_up, "losses": first,
            "peak_gib": peak_gib(device)}


def random_batch(batch: int, size: int, device) -> dict:
    import torch

    generator = torch.Generator().manual_seed(0)
    K = torch.tensor([[0.5 * size, 0, size / 2], [0, 0.5 * size, size / 2], [0, 0, 1.0]])
    images = {k: torch.rand(batch, 3, size, size, generator=generator).to(device) for k in ("prev", "cur", "next")}
    return {**images, "K": K.expand(batch, 3, 3).contiguous().to(device)}


def synchronise(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def peak_gib(device) -> float:
    """Peak memory of the timed steps: allocated by torch on CUDA, the process's maximum resident set on a CPU."""
    import resource

    import torch

    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def run_variant(args: argparse.Namespace, variant: str) -> dict:
    """``variant``'s figures from a fresh process (``before`` with the baseline's package first on the path)."""
    tree = args.baseline.resolve() if variant == "before" else ROOT
    env = environment_importing(tree)
    command = [sys.executable, __file__, "--worker", variant, "--baseline", str(args.baseline), "--preset",
               args.preset, "--size", str(args.size), "--batch", str(args.batch), "--device", args.device,
               "--precision", args.precision, "--steps", str(args.steps), "--threads", str(args.threads)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"variant {variant} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def largest_loss_difference(losses: dict[str, float], reference: dict[str, float]) -> tuple[str, float]:
    """The loss term farthest from ``reference``'s, relative to it, over the terms both computed."""
    shared = [k for k in reference if k in losses]
    return max(((k, abs(losses[k] - reference[k]) / max(abs(reference[k]), 1e-12)) for k in shared),
               key=lambda item: item[1])


def main() -> None:
    args = parse_args()
    on_gpu = args.device.startswith("cuda")
    args.batch = args.batch or (12 if on_gpu else 2)
    args.precision = args.precision or ("bf16" if on_gpu else "float32")
    args.steps = args.steps or (20 if on_gpu else 3)
    if args.worker:
        print(json.dumps(run_worker(args)))
        return
    variants = [v for v in VARIANTS if not (args.no_compile and v == "compiled")]
    rounds: dict[str, list[dict]] = {v: [] for v in variants}
    for round_index in range(args.rounds):
        for variant in variants:
            rounds[variant].append(run_variant(args, variant))
            print(f"round {round_index + 1}/{args.rounds} {variant}: "
                  f"{rounds[variant][-1]['median_s'] * 1000:.1f} ms/step", flush=True)
    print(f"\n{args.preset}, {args.size}x{args.size}, batch {args.batch}, {args.precision} on {args.device}, "
          f"{args.threads} CPU threads, {args.steps} timed steps, {args.rounds} round(s); before: {args.baseline}")
    print(f"{'variant':10s} {'ms/step':>9s} {'samples/s':>10s} {'warm-up s':>10s} {'peak GiB':>9s} "
          f"{'x before':>9s}  largest loss difference from before")
    base = statistics.median(r["median_s"] for r in rounds["before"])
    for variant in variants:
        seconds = statistics.median(r["median_s"] for r in rounds[variant])
        last = rounds[variant][-1]
        term, difference = largest_loss_difference(last["losses"], rounds["before"][-1]["losses"])
        print(f"{variant:10s} {seconds * 1000:9.1f} {args.batch / seconds:10.2f} {last['warm_up_s']:10.1f} "
              f"{last['peak_gib']:9.2f} {base / seconds:9.2f}  {term}: {difference:.2e}")


if __name__ == "__main__":
    main()
