"""Renderer speed: frames per second per layout, and the time to generate the default data set.

Usage: ``python benchmarks/bench_synth.py [--frames 20] [--size 128] [--device cpu] [--skip-default]``.
Part 1 renders one short sequence per layout in this process (one thread, as a worker does) and prints
frames per second, setup (geometry, texture) excluded. Part 2 writes the default data set of
``Params().synth`` (all three layouts, ``synth.workers`` processes) into a temporary folder and prints the
wall time of each layout and the total, the number the 3-minute budget refers to.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import torch

from endoflow.config import Params
from endoflow.data.scenenet import scenenet_intrinsics
from endoflow.synth.render import render_tube_frame
from endoflow.synth.rooms import render_room
from endoflow.data.base import DATASETS
from endoflow.synth.writers import (
    plan_jobs,
    room_sequence,
    scenenet_shape,
    simcol_intrinsics,
    synthesize_layout,
    tube_sequence,
    unitycam_intrinsics,
)


def frames_per_second(layout: str, frames: int, size: int, device: str) -> float:
    """Rendering speed of one sequence of ``layout`` (setup excluded)."""
    job = plan_jobs(layout, Path("unused"), 1, frames, size, 0, device, Params())[0]
    if layout == "scenenet":
        room, poses = room_sequence(job)
        height, width = scenenet_shape(size)
        K = scenenet_intrinsics(height, width)
        render = lambda pose: render_room(room, pose, K, height, width, torch.device(device))  # noqa: E731
    else:
        sequence = tube_sequence(job)
        K = simcol_intrinsics(size) if layout == "simcol" else unitycam_intrinsics(size)
        poses = sequence.poses
        render = lambda pose: render_tube_frame(sequence.scene, pose, K, size, size)  # noqa: E731
    render(poses[0])
    started = time.perf_counter()
    for pose in poses:
        render(pose)
    return len(poses) / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--size", type=int, default=Params().synth.size)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-default", action="store_true", help="only measure frames per second")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for layout in DATASETS:
        fps = frames_per_second(layout, args.frames, args.size, args.device)
        print(f"{layout:9s} {args.size}px  {fps:6.1f} frames/s (one thread, {args.device})", flush=True)
    if args.skip_default:
        return
    params = Params()
    started, cpu_started = time.perf_counter(), _cpu_seconds()
    with tempfile.TemporaryDirectory() as folder:
        for layout in DATASETS:
            print(synthesize_layout(layout, Path(folder) / layout, params=params, device=args.device), flush=True)
    cpu = _cpu_seconds() - cpu_started
    print(
        f"default data set: {time.perf_counter() - started:.1f} s wall in total (budget 180 s); "
        f"{cpu:.1f} CPU s, i.e. {cpu / params.synth.workers:.1f} s on {params.synth.workers} otherwise idle cores"
    )


def _cpu_seconds() -> float:
    """CPU time of this process and its finished worker processes."""
    own, workers = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + workers.ru_utime + workers.ru_stime


if __name__ == "__main__":
    main()
