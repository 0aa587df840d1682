"""The paper configuration at full scale on this machine's accelerator (or CPU): the figures of issue 10, section 6.

    python benchmarks/bench_paper_scale.py [--preset presets/paper.yaml] [--device auto] [--batch B]
                                           [--steps 20] [--gan-steps 20] [--eval-batches 10] [--threads T]
                                           [--peak-tflops P]

Shards: the real SimCol3D sample's frames (475 x 475) repeated into a SimCol3D layout and preprocessed by the
real ``preprocess_dataset`` to 480 x 480 shards (as ``bench_loader.py``). With the preset's model (its latent
bank randomly initialised: the same compute as a pretrained one) on ``--device``:

- training, float32 and bf16 autocast in turn: ``--steps`` steps of ``training_step_losses`` + AdamW at batch
  ``--batch`` (default: ``train.batch_size`` on a GPU, 2 on a CPU) fed by the training loader
  (``rank_batches`` with the preset's ``train.loader_workers`` on a GPU, one process on a CPU, pinned memory
  on CUDA); printed: samples/s,
  the fraction of step time spent waiting for the loader (target below 5%), peak memory (CUDA: allocated
  by torch; CPU: this process's maximum resident set) and achieved TFLOP/s, the step's FLOPs counted once with
  ``torch.utils.flop_counter`` (convolutions and matrix products only), against ``--peak-tflops`` (default:
  the dense bf16 peak of a known GPU; none on a CPU). The first step is a warm-up and not timed.
- latent-bank pretraining (``train_gan``, the preset's bank and critic, ``latent_bank.precision``):
  ``--gan-steps`` generator steps at each resolution on random maps; steps/s over all resolutions.
- evaluation: depth and pose of ``--eval-batches`` batches of ``eval.batch_size`` frames (CPU: 2) in
  ``eval.precision``; frames/s.

Figures are printed, not asserted: they depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from bench_loader import write_shards
from endoflow.config import Params, Precision, load_params
from endoflow.data.loader import rank_batches
from endoflow.devices import autocast, batch_to_device, compute_dtype, resolve_device, to_compute_layout
from endoflow.models.endoflow_model import EndoflowModel, build_model
from endoflow.training.objective import training_step_losses
from endoflow.training.pretrain import train_gan

# Dense bf16 tensor-core peaks (TFLOP/s, no sparsity) of the GPUs we expect, from the vendors' data sheets.
BF16_PEAK_TFLOPS = {"H100": 989.0, "H200": 989.0, "A100": 312.0, "L40S": 362.0, "RTX 6000": 130.5}
CPU_BATCH = 2


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="presets/paper.yaml")
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    parser.add_argument("--batch", type=int, default=None, help="training batch (default: preset on GPU, 2 on CPU)")
    parser.add_argument("--steps", type=int, default=None, help="timed training steps (default: 20 GPU, 2 CPU)")
    parser.add_argument("--gan-steps", type=int, default=None, help="generator steps per resolution (20 GPU, 2 CPU)")
    parser.add_argument("--eval-batches", type=int, default=None, help="evaluation batches (default: 10 GPU, 2 CPU)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--loader-workers", type=int, default=None,
                        help="loader processes (default: train.loader_workers on a GPU, 1 on a CPU)")
    parser.add_argument("--peak-tflops", type=float, default=None, help="the device's bf16 peak (default: known GPUs)")
    parser.add_argument("--cudnn-benchmark", action="store_true",
                        help="let cuDNN time its convolution algorithms for these shapes first")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="also profile a bf16 training step: the N operators of most device time")
    return parser.parse_args()


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak_memory(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def peak_memory_gib(device: torch.device) -> float:
    """CUDA: the most memory torch held since the last reset; CPU: the process's maximum resident set so far."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def device_peak_tflops(device: torch.device, given: float | None) -> float | None:
    if given is not None or device.type != "cuda":
        return given
    name = torch.cuda.get_device_name(device)
    return next((peak for key, peak in BF16_PEAK_TFLOPS.items() if key in name), None)


# ---------------------------------------------------------------------------------------------- training
@dataclass(frozen=True)
class TrainingFigures:
    precision: str
    samples_per_second: float
    data_wait_fraction: float
    peak_memory_gib: float
    tflops: float


def step_flops(model: EndoflowModel, params: Params, batch: dict) -> int:
    """FLOPs of one forward and backward pass, as ``torch.utils.flop_counter`` counts them."""
    counter = FlopCounterMode(display=False)
    with counter:
        training_step_losses(model, batch, params.loss)["total"].backward()
    model.zero_grad(set_to_none=True)
    return counter.get_total_flops()


def profile_training_step(params: Params, urls: list[str], device: torch.device, batch_size: int, rows: int) -> str:
    """torch.profiler's table of the ``rows`` operators taking most device (else CPU) time in one bf16 training
    step, after two warm-up steps."""
    torch.manual_seed(params.seed)
    model = to_compute_layout(build_model(params, None), device, "bf16", params.data.size).train()
    batches = rank_batches(urls, 0, 1, batch_size, epoch=0, seed=params.seed)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    def step() -> None:
        batch = batch_to_device(next(batches), device, "bf16")
        with autocast(device, "bf16"):
            losses = training_step_losses(model, batch, params.loss)
        losses["total"].backward()
        synchronise(device)
        model.zero_grad(set_to_none=True)

    step(), step()
    with torch.profiler.profile(activities=activities) as profiler:
        step()
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    return profiler.key_averages().table(sort_by=key, row_limit=rows)


def measure_training(params: Params, urls: list[str], device: torch.device, precision: Precision, batch_size: int,
                     steps: int, loader_workers: int) -> TrainingFigures:
    """``steps`` timed training steps after one warm-up, fed by the training loader as the loop feeds them."""
    torch.manual_seed(params.seed)
    model = to_compute_layout(build_model(params, None), device, precision, params.data.size).train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=params.train.lr)
    batches = rank_batches(urls, 0, 1, batch_size, epoch=0, seed=params.seed,
                           loader_workers=loader_workers, pin_memory=device.type == "cuda")
    waiting = computing = 0.0
    flops = 0
    reset_peak_memory(device)
    for step in range(steps + 1):
        started = time.perf_counter()
        batch = batch_to_device(next(batches), device, precision)
        synchronise(device)
        loaded = time.perf_counter()
        with autocast(device, precision):
            losses = training_step_losses(model, batch, params.loss)
        optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        optimizer.step()
        synchronise(device)
        if step == 0:
            with autocast(device, precision):
                flops = step_flops(model, params, batch)
            continue
        waiting += loaded - started
        computing += time.perf_counter() - loaded
    total = waiting + computing
    return TrainingFigures(str(compute_dtype(device, precision)).removeprefix("torch."), steps * batch_size / total,
                           waiting / total, peak_memory_gib(device), flops * steps / computing / 1e12)


# ------------------------------------------------------------------------------------ pretraining, eval
def pretraining_steps_per_second(params: Params, device: torch.device, steps: int) -> tuple[float, int, int]:
    """Generator steps/s of ``train_gan`` over every resolution, ``steps`` at each, on random depth maps; with the
    number of steps and of resolutions."""
    cfg = params.latent_bank.replace(steps_per_stage=steps, device=str(device))
    params = params.replace(latent_bank=cfg)
    maps = torch.rand(256, 1, cfg.resolution, cfg.resolution, generator=torch.Generator().manual_seed(0)) * 2 - 1
    started = time.perf_counter()
    _, history = train_gan(params, maps, device, lambda record, step: None)
    synchronise(device)
    resolutions = len({record["resolution"] for record in history})
    return len(history) / (time.perf_counter() - started), len(history), resolutions


@torch.no_grad()
def evaluation_frames_per_second(params: Params, urls: list[str], device: torch.device, batch_size: int,
                                 batches: int) -> float:
    """Depth and pose (as ``evaluate`` computes them) of ``batches`` loader batches, after one warm-up."""
    precision = params.eval.precision
    model = to_compute_layout(build_model(params, None), device, precision, params.data.size).eval()
    loader = rank_batches(urls, 0, 1, batch_size, epoch=0, seed=params.seed)
    frames, seconds = 0, 0.0
    for index in range(batches + 1):
        batch = batch_to_device(next(loader), device, precision)
        synchronise(device)
        started = time.perf_counter()
        with autocast(device, precision):
            model.predict_depth(batch["cur"])
            model.predict_pose(batch["cur"], batch["next"])
        synchronise(device)
        if index:
            frames += batch["cur"].shape[0]
            seconds += time.perf_counter() - started
    return frames / seconds


def main() -> None:
    args = parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.backends.cudnn.benchmark = args.cudnn_benchmark
    params = load_params(args.preset)
    device = resolve_device(args.device, "--device")
    on_gpu = device.type == "cuda"
    batch = args.batch or (params.train.batch_size if on_gpu else CPU_BATCH)
    steps = args.steps or (20 if on_gpu else 2)
    gan_steps = args.gan_steps or (20 if on_gpu else 2)
    eval_batches = args.eval_batches or (10 if on_gpu else 2)
    eval_batch = params.eval.batch_size if on_gpu else CPU_BATCH
    loader_workers = args.loader_workers if args.loader_workers is not None else (
        params.train.loader_workers if on_gpu else 1)
    peak = device_peak_tflops(device, args.peak_tflops)
    name = torch.cuda.get_device_name(device) if on_gpu else f"CPU, {torch.get_num_threads()} threads"
    print(f"{args.preset} on {device} ({name}); 480 x 480, training batch {batch}, "
          f"{loader_workers} loader processes, {steps} timed steps per precision, "
          f"cuDNN benchmark {'on' if args.cudnn_benchmark else 'off'}")
    with tempfile.TemporaryDirectory(prefix="bench_paper_scale_") as tmp:
        frames = max(34, (steps + 2) * batch + 2)
        urls = write_shards(Path(tmp), "sample", sequences=1, frames=frames)
        figures = [measure_training(params, urls, device, precision, batch, steps, loader_workers)
                   for precision in ("float32", "bf16")]
        eval_fps = evaluation_frames_per_second(params, urls, device, eval_batch, eval_batches)
        if args.profile:
            print(profile_training_step(params, urls, device, batch, args.profile))
    gan_rate, gan_total, gan_resolutions = pretraining_steps_per_second(params, device, gan_steps)

    print(f"{'training':10s} {'samples/s':>10s} {'data wait':>10s} {'peak GiB':>9s} {'TFLOP/s':>8s} {'of peak':>8s}")
    for f in figures:
        share = f"{f.tflops / peak:.1%}" if peak else "n/a"
        print(f"{f.precision:10s} {f.samples_per_second:10.2f} {f.data_wait_fraction:10.1%} "
              f"{f.peak_memory_gib:9.2f} {f.tflops:8.2f} {share:>8s}")
    print(f"bf16 / float32 training samples/s: {figures[1].samples_per_second / figures[0].samples_per_second:.2f}")
    print(f"peak bf16 TFLOP/s used: {peak if peak else 'unknown for this device (pass --peak-tflops)'}")
    print(f"latent-bank pretraining ({params.latent_bank.precision}): {gan_rate:.2f} generator steps/s "
          f"({gan_total} steps over {gan_resolutions} resolutions, batch "
          f"{params.latent_bank.batch_size})")
    print(f"evaluation ({params.eval.precision}): {eval_fps:.2f} frames/s (batch {eval_batch}, depth + pose)")


if __name__ == "__main__":
    main()
