"""Preprocessing throughput: shards vs a bare decode-resize-encode loop, and 2 worker processes vs 1.

    python benchmarks/bench_preprocess.py [--source synthetic|sample | --root DIR] [--sequences N] [--frames F]
                                          [--native N] [--size S] [--repeats R]

``synthetic``: a SimCol3D-layout data set from the built-in renderer (``endoflow synth``; ``--sequences``
per scene), frames at ``--native`` pixels (default: the built-in data's size). ``sample``: the real
SimCol3D sample (475 x 475, 16-bit RGBA) repeated to the same layout, so decoding costs what it costs on
the real data. ``--root``: any SimCol3D root as it is.

The bare loop does only the image work every preprocessing run must do, with the same functions: decode,
crop and resize and PNG-encode each frame's colour once and each target frame's depth once. The ratio of
frame rates (preprocess / bare, target >= 0.8) is the cost of everything else: planning, the frame cache,
re-decoding neighbours across shard boundaries, tar writing, meta.json and the manifest. Frame rates count
the data set's frames. Both run single-process with single-threaded OpenCV; the 2-process time includes
starting the pool. Figures are printed, not asserted: they depend on the machine and its load. CPU
seconds are printed too: on a busy machine wall-clock speed-ups mean little, while ``2 x cpu(1) / cpu(2)``
bounds what two processes can gain on two idle cores (extra work in the pool shows up there).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from endoflow.config import Params
from endoflow.data.frame_encoding import depth_to_counts, encode_png, resize_depth, resize_rgb
from endoflow.data.registry import open_reader
from endoflow.data.shard_engines import single_threaded_opencv
from endoflow.data.shard_plan import DEPTH_UNIT_CM
from endoflow.data.shards import preprocess_dataset
from endoflow.synth.writers import synthesize_layout

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "samples" / "simcol3d" / "SyntheticColon_I"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("synthetic", "sample"), default="synthetic")
    parser.add_argument("--root", help="an existing SimCol3D root to measure instead (e.g. the real data)")
    parser.add_argument("--sequences", type=int, default=2, help="per scene (synthetic) or in all (sample)")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--native", type=int, default=Params().synth.size, help="synthetic frame size (pixels)")
    parser.add_argument("--size", type=int, default=128, help="stored size (data.size)")
    parser.add_argument("--repeats", type=int, default=3, help="best of this many timings")
    return parser.parse_args()


def synthetic_layout(root: Path, sequences: int, frames: int, native: int) -> None:
    """Render in a child process: this one then times preprocessing in the state a stage run has (the
    renderer's many objects left behind would slow every garbage collection during the timings)."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        pool.submit(synthesize_layout, "simcol", root, sequences, frames, native, 0).result()


def repeated_sample_layout(root: Path, sequences: int, frames: int) -> None:
    """SimCol3D layout whose sequences repeat the real sample's 10 frames (and pose lines) cyclically."""
    scene = root / "SyntheticColon_I"
    scene.mkdir(parents=True)
    shutil.copyfile(SAMPLE / "cam.txt", scene / "cam.txt")
    positions = (SAMPLE / "SavedPosition_S1.txt").read_text().splitlines()
    rotations = (SAMPLE / "SavedRotationQuaternion_S1.txt").read_text().splitlines()
    for s in range(1, sequences + 1):
        folder = scene / f"Frames_S{s}"
        folder.mkdir()
        for i in range(frames):
            for kind in ("FrameBuffer", "Depth"):
                shutil.copyfile(SAMPLE / "Frames_S1" / f"{kind}_{i % 10:04d}.png", folder / f"{kind}_{i:04d}.png")
        (scene / f"SavedPosition_S{s}.txt").write_text("\n".join(positions[i % 10] for i in range(frames)))
        (scene / f"SavedRotationQuaternion_S{s}.txt").write_text("\n".join(rotations[i % 10] for i in range(frames)))


@dataclass(frozen=True)
class Timing:
    wall: float
    cpu: float  # this process and its finished children (pool workers), user + system


@contextmanager
def timed(into: list[Timing]) -> Iterator[None]:
    wall, cpu = time.perf_counter(), _cpu_seconds()
    yield
    into.append(Timing(time.perf_counter() - wall, _cpu_seconds() - cpu))


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def bare_loop(params: Params) -> int:
    """Decode + resize + encode each frame's colour (and target frames' depth); returns the frame count.

    Listing the data set through its reader is included: preprocessing has to do it as well.
    """
    offset, size, frames = params.preprocess.neighbour_offset, params.data.size, 0
    sequences = open_reader(params.data.simcol.root, "simcol", params).sequences()
    with single_threaded_opencv():
        for sequence in sequences:
            for i in range(len(sequence)):
                encode_png(resize_rgb(sequence.load_rgb(i), size))
                frames += 1
                if offset <= i < len(sequence) - offset:
                    counts, _ = depth_to_counts(resize_depth(sequence.load_depth(i), size), DEPTH_UNIT_CM["simcol"])
                    encode_png(counts)
    return frames


def with_workers(params: Params, workers: int) -> Params:
    return params.replace(preprocess=params.preprocess.replace(workers=workers))


def main() -> None:
    args = parse_args()
    timings: dict[str, list[Timing]] = {"bare": [], "one": [], "two": []}
    with tempfile.TemporaryDirectory(prefix="bench_preprocess_") as tmp:
        root = Path(args.root) if args.root else Path(tmp) / "SimCol3D"
        if args.root is None and args.source == "synthetic":
            synthetic_layout(root, args.sequences, args.frames, args.native)
        elif args.root is None:
            repeated_sample_layout(root, args.sequences, args.frames)
        params = Params()
        params.data.size = args.size
        params.data.simcol.root = str(root)
        # one split holds every sequence here: smaller shards than the default keep both workers busy
        params.preprocess = params.preprocess.replace(samples_per_shard=32, shard_multiple=2)
        out = Path(tmp) / "shards"
        # interleaved and best-of-N: on a shared machine the minimum is the least disturbed run
        for _ in range(args.repeats):
            with timed(timings["bare"]):
                frames = bare_loop(params)
            with timed(timings["one"]):
                preprocess_dataset("simcol", with_workers(params, 1), out)
            with timed(timings["two"]):
                preprocess_dataset("simcol", with_workers(params, 2), out)
    wall = {name: min(t.wall for t in values) for name, values in timings.items()}
    cpu = {name: min(t.cpu for t in values) for name, values in timings.items()}
    print(f"data: {args.root or args.source}, {frames} frames -> {args.size} px, best of {args.repeats}")
    for name, label in (("bare", "bare decode+resize+encode loop"), ("one", "preprocess, 1 process"),
                        ("two", "preprocess, 2 processes")):
        print(f"{label:31s}: {frames / wall[name]:8.1f} frames/s  wall {wall[name]:6.2f} s  cpu {cpu[name]:6.2f} s")
    print(f"ratio 1 process / bare loop    : {wall['bare'] / wall['one']:8.2f} wall, {cpu['bare'] / cpu['one']:.2f} cpu"
          "   (target >= 0.8)")
    print(f"speed-up 2 processes / 1       : {wall['one'] / wall['two']:8.2f}x wall   (target >= 1.6x)")
    # On idle cores two processes cannot beat half their total CPU time: the load-independent bound.
    print(f"  bound on 2 idle cores        : {2 * cpu['one'] / cpu['two']:8.2f}x (2 x cpu(1 process) / cpu(2))")
    print(f"load average during the run    : {os.getloadavg()[0]:8.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
