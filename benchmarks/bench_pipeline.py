"""Throughput of the pipeline: training samples/s with 1 and 2 Ray workers, and evaluation frames/s.

Usage::

    python benchmarks/bench_pipeline.py [--size 128] [--frames 24] [--steps 6] [--workers 1 2] [--gpu]

Renders a small synthetic SimCol3D layout, shards it, writes a latent bank with random weights (same
compute as a pretrained one), then runs the real ``train`` stage code once per worker count (one epoch of
``--steps`` steps, default params otherwise) and the ``evaluate`` stage on the SimCol I/II test sequences.
Training samples/s is the global rate over the epoch's steps as the training loop measures it (Ray start-up
excluded, the first steps included); the wall time of each run is printed beside it. ``--gpu`` trains with
``ray.use_gpu`` (bf16 autocast, channels-last) and suits the paper's setting: ``--size 480 --batch 12``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from endoflow import tracking
from endoflow.config import Params
from endoflow.data.shards import preprocess_dataset
from endoflow.evaluation.evaluate import run_evaluation
from endoflow.models.endoflow_model import generator_spec
from endoflow.models.latent_bank import LatentBankGenerator, generator_payload
from endoflow.synth.writers import synthesize_layout
from endoflow.training.ray_trainer import train


def prepare_project(root: Path, size: int, frames: int, batch: int, steps: int, gpu: bool) -> Params:
    params = Params()
    params.data.size = size
    params.data.simcol.root = str(root / "raw" / "SimCol3D")
    params.preprocess = params.preprocess.replace(out=str(root / "shards"), samples_per_shard=32)
    params.train = params.train.replace(
        epochs=1, batch_size=batch, steps_per_epoch=steps, val_batches=1, log_every=1, image_examples=1,
        latent_bank=str(root / "latent_bank.pt"))
    params.train.shards = str(root / "shards" / "simcol")
    params.ray = params.ray.replace(use_gpu=gpu)
    params.eval = params.eval.replace(shards=str(root / "shards"))
    synthesize_layout("simcol", Path(params.data.simcol.root), sequences=5, frames=frames, size=size, seed=0)
    preprocess_dataset("simcol", params, root / "shards" / "simcol")
    torch.save(generator_payload(LatentBankGenerator(generator_spec(params))), root / "latent_bank.pt")
    return params


def training_rate(params: Params, root: Path, workers: int) -> tuple[float, float]:
    """(samples/s over the epoch's steps, wall seconds of the whole run) with ``workers`` Ray workers."""
    params.ray = params.ray.replace(num_workers=workers, storage_path=str(root / f"ray-{workers}"))
    params.train = params.train.replace(out=str(root / "models" / "endoflow.pt"))
    started = time.perf_counter()
    summary = train(params, root)
    wall = time.perf_counter() - started
    history = tracking.client(tracking.tracking_uri(params, root)).get_metric_history(
        summary["mlflow_run_id"], "samples_per_second")
    return max(history, key=lambda m: m.step).value, wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=Params().data.size, help="square image size (default: params)")
    parser.add_argument("--frames", type=int, default=24, help="frames per synthetic sequence")
    parser.add_argument("--batch", type=int, default=Params().train.batch_size)
    parser.add_argument("--steps", type=int, default=6, help="training steps per run")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--gpu", action="store_true", help="train on GPU workers (bf16)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as folder:
        root = Path(folder)
        params = prepare_project(root, args.size, args.frames, args.batch, args.steps, args.gpu)
        rows = []
        for workers in args.workers:
            rate, wall = training_rate(params, root, workers)
            rows.append(f"train  {workers} worker(s)  {rate:8.2f} samples/s   (run wall time {wall:.0f} s)")
        started = time.perf_counter()
        result = run_evaluation(params, "simcol_12", root)
        rows.append(f"evaluate simcol_12    {result['frames_per_second']:8.2f} frames/s    "
                    f"({result['frames']} frames, stage wall time {time.perf_counter() - started:.0f} s)")
    print(f"size {args.size}, batch {args.batch}, {torch.get_num_threads()} torch threads in the driver")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
