"""Can the loader feed the accelerator? Loader samples/s with 0, 1 and 2 loader processes beside the paper
model's training step at 480 x 480, in one run.

    python benchmarks/bench_loader.py [--source sample|synthetic] [--sequences 3] [--frames 34] [--repeats 3]
                                      [--preset presets/paper.yaml] [--step-batch 2] [--step-repeats 2]
                                      [--gpu-step-seconds S | --gpu-tflops 100]

Shards: ``sample`` (default) repeats the real SimCol3D sample's frames (475 x 475) into a SimCol3D layout,
``synthetic`` renders one with the built-in renderer at 480 px (minutes on 2 cores); either is preprocessed by
the real ``preprocess_dataset`` to 480 x 480 shards, all in the train split (``--sequences`` x (``--frames``
- 2) samples, default 96; ``synthetic`` renders ``--sequences`` per scene, of three). Loader: one rank reads every train shard through ``rank_batches`` in batches of
the preset's ``train.batch_size``, as training does (manifest checks, PNG decoding, collation); a whole epoch
is timed, best of ``--repeats`` with the three settings interleaved. Two rates: over the whole epoch, and after
the first round (every loader process has delivered its first batch): the start-up (forking, filling the shuffle
buffer, a first batch decoded) costs about half a second per epoch, much of a 96-sample epoch but nothing beside
a real one, so the speed-up and the ratio below use the second, the rate training runs at. CPU seconds
(this process and its reaped children) give ``2 x cpu(1) / cpu(2)``, the speed-up two idle cores would allow.
A control, interleaved with them, times plain SHA-256 hashing in 1 and in 2 processes: the speed-up the machine
offers two processes at that moment, against which the loader's is to be read on a shared machine.

Model: ``build_model`` with the preset's ``model``, ``latent_bank`` and ``loss`` sections read at run time (a
randomly initialised bank: same compute as a pretrained one), one forward, backward and AdamW step at 480 x 480
and ``--step-batch`` on this CPU in float32: its time per sample is printed. The same step under
``torch.utils.flop_counter`` counts its FLOPs (convolutions and matrix products; elementwise work, grid
sampling and the like are not counted, so a step derived from them is short and the demand on the loader high).

GPU: without ``--gpu-step-seconds`` (a measured step at the preset's batch size), the GPU step is derived as
FLOPs per sample x the preset's batch size / ``--gpu-tflops`` (default 100: the achieved bf16 rate assumed for
one A100/H100-class GPU on this convolutional network, a third of an A100's 312 TFLOP/s dense bf16 peak and a
tenth of an H100 SXM's 989). The ratio printed is loader samples/s per process over the samples/s the GPU
consumes; its inverse is the loader processes one GPU needs (``train.loader_workers``). Figures are printed, not
asserted: they depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from bench_preprocess import SAMPLE, repeated_sample_layout
from bench_train_step import make_batch, make_step
from endoflow.config import Params, load_params
from endoflow.data.loader import batches_per_epoch, list_shards, rank_batches
from endoflow.data.shards import preprocess_dataset
from endoflow.models.endoflow_model import build_model
from endoflow.synth.writers import synthesize_layout

SIZE = 480
LOADER_WORKERS = (0, 1, 2)
TARGET_SPEEDUP = 1.8


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("sample", "synthetic"), default="sample")
    parser.add_argument("--sequences", type=int, default=3, help="SimCol3D sequences (synthetic: per scene)")
    parser.add_argument("--frames", type=int, default=34, help="frames per sequence (samples: frames - 2)")
    parser.add_argument("--repeats", type=int, default=3, help="loader epochs per setting (best is reported)")
    parser.add_argument("--preset", default="presets/paper.yaml", help="params whose model and batch size to use")
    parser.add_argument("--step-batch", type=int, default=2, help="batch of the CPU training step")
    parser.add_argument("--step-repeats", type=int, default=2, help="timed CPU steps after a warm-up")
    parser.add_argument("--gpu-step-seconds", type=float, default=None,
                        help="a measured GPU training step at the preset's batch size (default: derived from FLOPs)")
    parser.add_argument("--gpu-tflops", type=float, default=100.0,
                        help="achieved bf16 TFLOP/s assumed for the GPU when --gpu-step-seconds is not given")
    return parser.parse_args()


# ------------------------------------------------------------------------------------------------ shards
def write_shards(root: Path, source: str, sequences: int, frames: int) -> list[str]:
    """480 x 480 train shards of a SimCol3D layout, written by the preprocessing stage's own code."""
    layout = root / "SimCol3D"
    if source == "sample":
        if not SAMPLE.is_dir():
            raise SystemExit(f"{SAMPLE}: the real SimCol3D sample is missing; use --source synthetic")
        repeated_sample_layout(layout, sequences, frames)
    else:
        render_in_child(layout, sequences, frames)
    params = Params()
    params.data.size = SIZE
    params.data.simcol = params.data.simcol.replace(root=str(layout), val=[], test=[])
    params.preprocess = params.preprocess.replace(samples_per_shard=16, shard_multiple=2)
    preprocess_dataset("simcol", params, root / "shards")
    return list_shards(root / "shards", "train")


def render_in_child(layout: Path, sequences: int, frames: int) -> None:
    """The renderer runs in a child process, leaving this one as a training process would be (bench_preprocess)."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        pool.submit(synthesize_layout, "simcol", layout, sequences, frames, SIZE, 0).result()


# ------------------------------------------------------------------------------------------------ loader
@dataclass(frozen=True)
class Epoch:
    samples: int
    wall: float  # the whole epoch, process start-up included
    first_round: float  # until each loader process has delivered a batch (in-process: the first batch)
    later_samples: int  # delivered after the first round
    cpu: float

    @property
    def rate(self) -> float:
        return self.samples / self.wall

    @property
    def steady_rate(self) -> float:
        return self.later_samples / (self.wall - self.first_round)


def loader_epoch(urls: list[str], batch_size: int, loader_workers: int) -> Epoch:
    """One epoch of one rank holding every shard, read as training reads it."""
    started, cpu, samples, first_round, round_samples = time.perf_counter(), _cpu_seconds(), 0, 0.0, 0
    batches = rank_batches(urls, 0, 1, batch_size, epoch=0, seed=0, loader_workers=loader_workers)
    for index, batch in enumerate(batches):
        samples += len(batch["key"])
        if index == max(loader_workers, 1) - 1:
            first_round, round_samples = time.perf_counter() - started, samples
    wall = time.perf_counter() - started
    return Epoch(samples, wall, first_round, samples - round_samples, _cpu_seconds() - cpu)


def hashing_seconds(processes: int) -> float:
    """Wall time of ``processes`` processes each hashing the same amount: the machine's parallelism now."""
    context = multiprocessing.get_context("fork")
    workers = [context.Process(target=_hash_blocks) for _ in range(processes)]
    started = time.perf_counter()
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return time.perf_counter() - started


def _hash_blocks(blocks: int = 400) -> None:
    data = bytes(1 << 20)
    for _ in range(blocks):
        hashlib.sha256(data).digest()


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


# ------------------------------------------------------------------------------------------------- model
@dataclass(frozen=True)
class Step:
    seconds: float  # best of the timed steps
    flops: int  # of one step, as torch.utils.flop_counter counts them
    batch: int
    parameters: int


def cpu_step(params: Params, batch_size: int, repeats: int) -> Step:
    """The paper model's training step at 480 x 480 on this CPU (float32), and its FLOPs."""
    model = build_model(params, None).train()
    step = make_step(model, params, make_batch(batch_size, SIZE, torch.device("cpu")), torch.device("cpu"), False)
    counter = FlopCounterMode(display=False)
    with counter:
        step()  # also the warm-up
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        step()
        times.append(time.perf_counter() - started)
    return Step(min(times), counter.get_total_flops(), batch_size, sum(p.numel() for p in model.parameters()))


# ------------------------------------------------------------------------------------------------ report
def main() -> None:
    args = parse_args()
    params = load_params(args.preset)
    batch_size = params.train.batch_size
    epochs: dict[int, list[Epoch]] = {workers: [] for workers in LOADER_WORKERS}
    hashing: dict[int, list[float]] = {1: [], 2: []}
    with tempfile.TemporaryDirectory(prefix="bench_loader_") as tmp:
        urls = write_shards(Path(tmp), args.source, args.sequences, args.frames)
        if batches_per_epoch(urls, 1, batch_size) <= max(LOADER_WORKERS):
            raise SystemExit(f"fewer than {max(LOADER_WORKERS) + 1} batches of {batch_size}: every loader process "
                             f"needs a batch after its first; raise --sequences or --frames")
        shard_bytes = sum(Path(url).stat().st_size for url in urls)
        for _ in range(args.repeats):  # interleaved: load from other processes hits every setting alike
            for workers in LOADER_WORKERS:
                epochs[workers].append(loader_epoch(urls, batch_size, workers))
            for processes, seconds in hashing.items():
                seconds.append(hashing_seconds(processes))
    step = cpu_step(params, args.step_batch, args.step_repeats)

    best = {workers: min(runs, key=lambda e: e.wall) for workers, runs in epochs.items()}
    cpu = {workers: min(e.cpu for e in runs) for workers, runs in epochs.items()}
    rate = {workers: max(e.steady_rate for e in runs) for workers, runs in epochs.items()}
    samples = best[0].samples
    flops_per_sample = step.flops / step.batch
    if args.gpu_step_seconds is None:
        gpu_step = flops_per_sample * batch_size / (args.gpu_tflops * 1e12)
        gpu_source = (f"ASSUMED: FLOPs/sample x batch {batch_size} / {args.gpu_tflops:g} achieved TFLOP/s "
                      f"(no GPU measured; pass --gpu-step-seconds)")
    else:
        gpu_step = args.gpu_step_seconds
        gpu_source = f"measured, given with --gpu-step-seconds, batch {batch_size}"
    gpu_rate = batch_size / gpu_step
    speedup = rate[2] / rate[1]

    print(f"shards: {args.source}, {samples} samples at {SIZE}x{SIZE} in {len(urls)} shards "
          f"({shard_bytes / samples / 1e6:.2f} MB/sample), loader batch {batch_size} ({args.preset}), "
          f"best of {args.repeats}")
    print(f"{'loader':32s} {'samples/s after 1st round':>26s} {'in the epoch':>13s} {'1st round s':>12s} "
          f"{'epoch s':>8s} {'cpu s':>6s}")
    for workers in LOADER_WORKERS:
        label = "in the training process (0)" if workers == 0 else f"{workers} loader process{'es' * (workers > 1)}"
        epoch = best[workers]
        print(f"  {label:30s} {rate[workers]:26.1f} {epoch.rate:13.1f} {epoch.first_round:12.2f} {epoch.wall:8.2f} "
              f"{cpu[workers]:6.2f}")
    verdict = "meets" if speedup >= TARGET_SPEEDUP else "misses"
    machine = 2 * min(hashing[1]) / min(hashing[2])
    print(f"speed-up 2 processes / 1: {speedup:.2f}x after the first round ({verdict} the {TARGET_SPEEDUP}x target), "
          f"{best[2].rate / best[1].rate:.2f}x over the whole epoch; bound on 2 idle cores 2 x cpu(1) / cpu(2) = "
          f"{2 * cpu[1] / cpu[2]:.2f}x")
    print(f"control, plain hashing in 2 processes vs 1 (twice the work): {machine:.2f}x the throughput; "
          f"the loader reaches {speedup / machine:.2f} of that")
    per_sample = step.seconds / step.batch
    print(f"training step, paper model ({step.parameters / 1e6:.1f} M parameters), {SIZE}x{SIZE}, batch "
          f"{step.batch}, CPU float32, {torch.get_num_threads()} threads: {step.seconds:.2f} s = "
          f"{per_sample:.2f} s/sample ({1 / per_sample:.2f} samples/s)")
    print(f"FLOPs per sample (forward + backward, flop_counter): {flops_per_sample / 1e9:.1f} GFLOP")
    print(f"GPU step at batch {batch_size}: {gpu_step * 1000:.0f} ms, {gpu_source}")
    print(f"samples/s a GPU step consumes: {gpu_rate:.1f}")
    ratio = rate[1] / gpu_rate
    print(f"ratio loader samples/s per process / GPU samples/s: {rate[1]:.1f} / {gpu_rate:.1f} = {ratio:.3f} "
          f"-> {math.ceil(1 / ratio)} loader processes per GPU at this per-process rate")
    print(f"load average during the run: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
