"""`endoflow reconstruct`: its speed at the model's size and at 480 x 480, and whether a long video needs more
memory than a short one, in one run.

    python benchmarks/bench_reconstruct.py [--frames 60] [--size 480] [--short 600] [--long 6000]
                                           [--video-size 128] [--measure-frames 3] [--repeats 1] [--threads 2]
                                           [--device cpu] [--parts speed memory measuring]

Model: the default model (``Params().model``: latent bank on) at ``data.size`` 64, randomly initialised and
written as a model file (``save_model_file``): weights do not change speed.

Speed: a synthetic SimCol3D layout rendered at 480 px (``synthesize_layout``, ``--frames`` per sequence),
sequence S1 read through ``open_frames`` as dataset input (with its ground truth, as a user's dataset run). The
whole ``reconstruct()`` call (model load, inference, fusion, every write) is timed at size 64 (the model's) and
at ``--size``, with fusion on and off, after an untimed warm-up run; frames/s is frames over the call's wall
time, best of ``--repeats``. The split of the fused run's time: model load and frame reading (decoding the
dataset's PNGs, crop and resize) and the model's depth and pose per frame, each timed alone on the same frames;
writes = the unfused call minus those three (every output file and picture, the ground-truth scale: all
reconstruct does besides); fusion = the fused call minus the unfused one. On a machine shared with other work
the differences can come out small or negative at size 64, where the parts take tenths of a second: use
``--repeats``.

Memory: two MP4 (H.264) videos of ``--short`` and ``--long`` frames at ``--video-size`` px, cycling a few
rendered frames with small shifts (cheap to make, but every frame is decoded), are reconstructed without
fusion (its surface is an output that grows with what the camera saw) at the model's size, each in a fresh
spawned process. Printed per video: the process's peak resident set (``VmHWM``; not ``ru_maxrss``, which a
spawned child inherits from its parent, see :func:`peak_resident_mib`), its peak from an early frame on (the
100th or the one a tenth of the way in, whichever is later: the kernel's peak is restarted there through
``/proc/self/clear_refs``, as start-up can peak higher than streaming and hide growth below the difference),
the resident set when that early frame and the last one were read, and on CUDA torch's peak allocation; then
the long/short ratios of the peaks, which should be about 1. What legitimately grows per frame is the camera
path (a 4 x 4 pose, a timestamp and an index: a few hundred bytes), the output video's index (tens of bytes)
and the files on disk. Linux only (``/proc``).

Measuring: the first ``--measure-frames`` frames of the speed scene (rendered again if the speed part is not
run) are reconstructed at ``--size`` with fusion and measured (``measure_reconstruction``, the ``reconstruct``
stage's measure: five more fusions and eleven nearest-neighbour searches) twice in one run: with the k-d tree
settings of ``capped_distances`` and with scipy's defaults (leaves of 16 points, one core). The model file's
baselines are flat (a constant-velocity step of zero), so the constant-velocity and trivial rows lie
centimetres off the surface: the slow case of a nearest-neighbour search.

Figures are printed, not asserted: they depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from endoflow.config import Params
from endoflow.data.frame_encoding import resize_rgb
from endoflow.devices import images_to_device, resolve_device
from endoflow.io import atomic_path
from endoflow.models.endoflow_model import build_model, load_trained_model
from endoflow.models.model_file import ModelRecord, TrainingBaselines, load_model_file, save_model_file
from endoflow.reconstruction import measure
from endoflow.reconstruction.frames import FrameRange, FrameSource, InputFrame, open_frames
from endoflow.reconstruction.reconstruct import ReconstructOptions, reconstruct
from endoflow.synth.writers import synthesize_layout

MODEL_SIZE = 64
RENDER_SIZE = 480
SEQUENCE = "S1"
WARM_UP_FRAMES = 3
DISTINCT_FRAMES = 8  # rendered frames the memory videos cycle through
MAX_SHIFT_PX = 8  # each cycle shifts them one more pixel sideways, up to this
VIDEO_FPS = 30
EARLY_FRAME_MIN = 100
MIB = 2**20


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="frames of the speed run's sequence")
    parser.add_argument("--size", type=int, default=RENDER_SIZE, help="the large model input of the speed run")
    parser.add_argument("--short", type=int, default=600, help="frames of the short video (memory)")
    parser.add_argument("--long", type=int, default=6000, help="frames of the long video (memory)")
    parser.add_argument("--video-size", type=int, default=128, help="native frame size of the memory videos")
    parser.add_argument("--measure-frames", type=int, default=3, help="frames of the measuring run")
    parser.add_argument("--repeats", type=int, default=1, help="timed speed runs per setting (best is reported)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--parts", nargs="+", choices=("speed", "memory", "measuring"),
                        default=["speed", "memory", "measuring"])
    return parser.parse_args()


def model_params() -> Params:
    params = Params()
    params.data.size = MODEL_SIZE
    return params


def write_untrained_model_file(path: Path, params: Params) -> Path:
    """A model file of the randomly initialised default model, with flat baselines (unused by reconstruct)."""
    torch.manual_seed(0)
    model = build_model(params, latent_bank_path=None)
    baselines = TrainingBaselines(mean_depth_cm=7.0,
                                  mean_depth_map=np.full((MODEL_SIZE, MODEL_SIZE), 7.0, np.float32),
                                  mean_relative_pose=np.eye(4))
    save_model_file(path, ModelRecord(params=params, state=model.state_dict(), epoch=0, val={},
                                      mlflow_run_id=None, baselines=baselines))
    return path


def render_scene(root: Path, frames: int, size: int, params: Params, threads: int, device: str) -> FrameSource:
    """Sequence S1 of a synthetic SimCol3D layout (the layout renders three; S1 is read)."""
    synthesize_layout("simcol", root, sequences=1, frames=frames, size=size, seed=0, params=params,
                      workers=threads, device=device)
    return open_frames(root, SEQUENCE, params)


def quietly_reconstruct(source: FrameSource, K: np.ndarray, model_file: Path, out: Path,
                        options: ReconstructOptions) -> dict:
    """``reconstruct`` without its progress lines (errors still surface as exceptions)."""
    with open(os.devnull, "w") as nowhere, contextlib.redirect_stderr(nowhere):
        return reconstruct(source, K, model_file, out, options)


# ------------------------------------------------------------------------------------------------- speed
@dataclass
class SpeedRun:
    size: int
    fuse: bool
    frames: int
    seconds: float

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds


@dataclass
class SpeedSplit:
    """Seconds of the fused run spent on each part (see the module docstring)."""

    load: float
    read: float
    model: float
    writes: float
    fusion: float

    @property
    def total(self) -> float:
        return self.load + self.read + self.model + self.writes + self.fusion


def timed_reconstruct(source: FrameSource, model_file: Path, out: Path, size: int, fuse: bool, device: str,
                      selection: FrameRange = FrameRange()) -> SpeedRun:
    options = ReconstructOptions(frames=selection, size=size, fuse=fuse, device=device)
    started = time.perf_counter()
    summary = quietly_reconstruct(source, source.K, model_file, out, options)
    seconds = time.perf_counter() - started
    shutil.rmtree(out)
    return SpeedRun(size, fuse, summary["frames"], seconds)


def best_runs(source: FrameSource, model_file: Path, work: Path, size: int, device: str,
              repeats: int) -> dict[bool, SpeedRun]:
    """Fused and unfused calls, alternating so that load from other processes hits both alike; the fastest."""
    timed_reconstruct(source, model_file, work / "warm-up", size, True, device, FrameRange(stop=WARM_UP_FRAMES))
    runs: dict[bool, list[SpeedRun]] = {True: [], False: []}
    for _ in range(repeats):
        for fuse in (True, False):
            runs[fuse].append(timed_reconstruct(source, model_file, work / "out", size, fuse, device))
    return {fuse: min(found, key=lambda run: run.seconds) for fuse, found in runs.items()}


def read_frames(source: FrameSource, size: int) -> tuple[float, list[np.ndarray]]:
    """Seconds to read every frame (with its ground truth) and crop and resize it, and the images."""
    started = time.perf_counter()
    images = [resize_rgb(frame.rgb, size) for frame in source.frames(FrameRange())]
    return time.perf_counter() - started, images


@torch.no_grad()
def model_seconds(model: torch.nn.Module, images: list[np.ndarray], device: torch.device) -> float:
    """Depth of every frame and pose of every consecutive pair, one frame at a time and brought back to the
    CPU, as reconstruct runs them (after an untimed first frame: first-call allocations)."""
    def infer(previous: Optional[torch.Tensor], rgb: np.ndarray) -> torch.Tensor:
        image = images_to_device(torch.from_numpy(rgb).permute(2, 0, 1)[None].contiguous(), device, "float32")
        model.predict_depth(image)[0, 0].cpu()
        if previous is not None:
            model.predict_pose(previous, image)[0].cpu()
        return image

    infer(None, images[0])
    previous = None
    started = time.perf_counter()
    for rgb in images:
        previous = infer(previous, rgb)
    return time.perf_counter() - started


def speed_split(source: FrameSource, model_file: Path, size: int, device: str,
                runs: dict[bool, SpeedRun]) -> SpeedSplit:
    torch_device = resolve_device(device, "--device")
    started = time.perf_counter()
    model, _ = load_trained_model(model_file, torch_device)
    load = time.perf_counter() - started
    read, images = read_frames(source, size)
    model_time = model_seconds(model, images, torch_device)
    return SpeedSplit(load=load, read=read, model=model_time,
                      writes=runs[False].seconds - load - read - model_time,
                      fusion=runs[True].seconds - runs[False].seconds)


def measure_speed(args: argparse.Namespace, work: Path, params: Params, model_file: Path
                  ) -> list[tuple[dict[bool, SpeedRun], SpeedSplit]]:
    started = time.perf_counter()
    source = render_scene(work / "SimCol3D", args.frames, RENDER_SIZE, params, args.threads, args.device)
    print(f"speed input: {source.description}, {source.length} frames of {RENDER_SIZE} px "
          f"(rendered in {time.perf_counter() - started:.0f} s)")
    results = []
    for size in (MODEL_SIZE, args.size):
        runs = best_runs(source, model_file, work, size, args.device, args.repeats)
        split = speed_split(source, model_file, size, args.device, runs)
        for run in runs.values():
            print(f"  size {size:4d} fusion {'on ' if run.fuse else 'off'}: {run.frames} frames in "
                  f"{run.seconds:6.1f} s = {run.frames_per_second:6.2f} frames/s")
        results.append((runs, split))
    return results


# --------------------------------------------------------------------------------------------- measuring
def scipy_default_distances(targets: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``capped_distances`` with scipy's k-d tree defaults: leaves of 16 points, one core."""
    distances, _ = cKDTree(targets).query(points, distance_upper_bound=measure.DISTANCE_CAP_CM)
    return np.minimum(distances, measure.DISTANCE_CAP_CM)


def timed_measure(source: FrameSource, out: Path, baselines: TrainingBaselines) -> tuple[float, dict]:
    with open(os.devnull, "w") as nowhere, contextlib.redirect_stderr(nowhere):
        started = time.perf_counter()
        result = measure.measure_reconstruction(source, out, baselines)
        return time.perf_counter() - started, result


def measure_measuring(args: argparse.Namespace, work: Path, params: Params, model_file: Path) -> dict[str, float]:
    """Seconds of ``measure_reconstruction`` with our k-d tree settings and with scipy's defaults."""
    root = work / "SimCol3D"
    source = open_frames(root, SEQUENCE, params) if root.exists() else render_scene(
        root, args.measure_frames, RENDER_SIZE, params, args.threads, args.device)
    out = work / "measured"
    options = ReconstructOptions(frames=FrameRange(stop=args.measure_frames), size=args.size, device=args.device)
    quietly_reconstruct(source, source.K, model_file, out, options)
    baselines = load_model_file(model_file).baselines
    ours, result = timed_measure(source, out, baselines)
    ours_distances = measure.capped_distances
    measure.capped_distances = scipy_default_distances
    try:
        defaults, default_result = timed_measure(source, out, baselines)
    finally:
        measure.capped_distances = ours_distances
    figures = [[row[key] for row in found["surface"].values() for key in sorted(row)]
               for found in (result, default_result)]
    if not np.array_equal(*figures, equal_nan=True):
        raise AssertionError("the two k-d tree settings measured different surface errors")
    print(f"measuring: {args.measure_frames} frames at {args.size} px, voxel {result['voxel_cm']:.3g} cm")
    return {"ours": ours, "scipy defaults": defaults}


# ------------------------------------------------------------------------------------------------ memory
@dataclass(frozen=True)
class MemoryJob:
    video: Path
    frames: int
    K: np.ndarray
    model_file: Path
    out: Path
    threads: int
    device: str


@dataclass
class MemoryRun:
    """MiB: ``peak_rss`` of the whole process, ``streaming_peak_rss`` from frame ``early`` to the end (start-up,
    which loads the model, excluded), ``rss_early``/``rss_last`` when frame ``early``/the last frame was read."""

    frames: int
    seconds: float
    peak_rss_mib: float
    streaming_peak_rss_mib: float
    rss_early_mib: float
    rss_last_mib: float
    cuda_peak_mib: Optional[float]

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds


def early_frame(frames: int) -> int:
    """The 100th frame or the one a tenth of the way in, whichever is later (the last for a shorter video): by
    then start-up allocations are done, the H.264 encoder's look-ahead of the side-by-side video among them
    (tens of frames), so growth is measured from it."""
    return min(frames, max(EARLY_FRAME_MIN, frames // 10))


def resident_mib() -> float:
    """This process's resident set now (Linux ``/proc/self/statm``)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / MIB


def peak_resident_mib() -> float:
    """This process's peak resident set since it started or since :func:`reset_peak_resident` (``VmHWM``).

    Not ``ru_maxrss``: Linux carries the maximum of the image an ``exec`` replaces into it, and a spawned child
    is execed from a fork of its parent, so its ``ru_maxrss`` starts at the parent's resident set."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("VmHWM:"))
    return int(line.split()[1]) / 1024


def reset_peak_resident() -> None:
    """Restart the kernel's peak resident set (``VmHWM``) from the current one."""
    with open("/proc/self/clear_refs", "w") as clear_refs:
        clear_refs.write("5")


class ResidentSetProbe(FrameSource):
    """Passes a source's frames through, noting the resident set when frame ``early`` and the last frame are
    handed over, and at ``early`` the start-up peak, restarting the peak from there. Holds nothing per frame."""

    def __init__(self, inner: FrameSource, early: int) -> None:
        self.inner, self.early = inner, early
        self.description, self.native_size, self.K = inner.description, inner.native_size, inner.K
        self.location = inner.location
        self.length, self.fps = inner.length, inner.fps
        self.early_mib = self.last_mib = self.startup_peak_mib = float("nan")

    def frames(self, selection: FrameRange) -> Iterator[InputFrame]:
        for count, frame in enumerate(self.inner.frames(selection), start=1):
            self.last_mib = resident_mib()
            if count == self.early:
                self.early_mib, self.startup_peak_mib = self.last_mib, peak_resident_mib()
                reset_peak_resident()
            yield frame


def reconstruct_video(job: MemoryJob) -> MemoryRun:
    """Runs in a fresh process: the whole reconstruct call on the video, without fusion."""
    torch.set_num_threads(job.threads)
    source = ResidentSetProbe(open_frames(job.video, None, Params()), early=early_frame(job.frames))
    started = time.perf_counter()
    summary = quietly_reconstruct(source, job.K, job.model_file, job.out,
                                  ReconstructOptions(fuse=False, device=job.device))
    seconds = time.perf_counter() - started
    streaming_peak = peak_resident_mib()
    device = resolve_device(job.device, "--device")
    cuda_peak = torch.cuda.max_memory_allocated(device) / MIB if device.type == "cuda" else None
    return MemoryRun(summary["frames"], seconds, max(source.startup_peak_mib, streaming_peak), streaming_peak,
                     source.early_mib, source.last_mib, cuda_peak)


def in_fresh_process(job: MemoryJob) -> MemoryRun:
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(reconstruct_video, job).result()


def shifted_cycle(distinct: list[np.ndarray], count: int) -> Iterator[np.ndarray]:
    """``count`` frames: the distinct ones in turn, shifted one pixel further sideways every cycle."""
    for index in range(count):
        cycle, position = divmod(index, len(distinct))
        yield np.roll(distinct[position], cycle % MAX_SHIFT_PX, axis=1)


def write_video(path: Path, frames: Iterator[np.ndarray], size: int) -> Path:
    import av

    with atomic_path(path) as temporary, av.open(str(temporary), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=VIDEO_FPS, options={"preset": "ultrafast"})
        stream.width, stream.height, stream.pix_fmt = size, size, "yuv420p"
        for rgb in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
        container.mux(stream.encode())
    return path


def measure_memory(args: argparse.Namespace, work: Path, params: Params, model_file: Path) -> dict[str, MemoryRun]:
    scene = render_scene(work / "VideoScene", DISTINCT_FRAMES, args.video_size, params, args.threads, args.device)
    distinct = [frame.rgb for frame in scene.frames(FrameRange())]
    runs = {}
    for label, count in (("short", args.short), ("long", args.long)):
        started = time.perf_counter()
        video = write_video(work / f"{label}.mp4", shifted_cycle(distinct, count), args.video_size)
        encoded = time.perf_counter() - started
        run = in_fresh_process(MemoryJob(video, count, scene.K, model_file, work / f"out-{label}", args.threads,
                                         args.device))
        shutil.rmtree(work / f"out-{label}")
        video.unlink()
        print(f"  {label:5s} video: {count} frames ({count / VIDEO_FPS / 60:.1f} min at {VIDEO_FPS} fps, encoded in "
              f"{encoded:.0f} s): {run.frames_per_second:.1f} frames/s, peak RSS {run.peak_rss_mib:.0f} MiB")
        runs[label] = run
    return runs


# ------------------------------------------------------------------------------------------------ report
def print_speed_table(results: list[tuple[dict[bool, SpeedRun], SpeedSplit]]) -> None:
    print(f"\n{'speed':20s} {'frames':>6s} {'seconds':>8s} {'frames/s':>9s}")
    for runs, _ in results:
        for run in runs.values():
            label = f"size {run.size}, fusion {'on' if run.fuse else 'off'}"
            print(f"{label:20s} {run.frames:6d} {run.seconds:8.1f} {run.frames_per_second:9.2f}")
    for runs, _ in results[1:]:
        small, large = results[0][0][True], runs[True]
        print(f"fused frames/s, size {small.size} / size {large.size}: "
              f"{small.frames_per_second / large.frames_per_second:.2f}x")
    print(f"\n{'split of fused run':20s} {'load':>13s} {'read':>13s} {'model':>13s} {'writes':>13s} {'fusion':>13s}")
    for runs, split in results:
        parts = (split.load, split.read, split.model, split.writes, split.fusion)
        cells = " ".join(f"{seconds:6.1f}s {seconds / split.total:5.0%}" for seconds in parts)
        print(f"{'size ' + str(runs[True].size):20s} {cells}")


def print_memory_table(runs: dict[str, MemoryRun]) -> None:
    print(f"\n{'memory (no fusion)':20s} {'frames':>6s} {'frames/s':>9s} {'peak RSS':>9s} {'later':>9s} "
          f"{'RSS early':>9s} {'RSS @end':>9s} {'CUDA peak':>10s}  (MiB)")
    for label, run in runs.items():
        cuda = f"{run.cuda_peak_mib:10.0f}" if run.cuda_peak_mib is not None else f"{'n/a':>10s}"
        print(f"{label:20s} {run.frames:6d} {run.frames_per_second:9.1f} {run.peak_rss_mib:9.0f} "
              f"{run.streaming_peak_rss_mib:9.0f} {run.rss_early_mib:9.0f} {run.rss_last_mib:9.0f} {cuda}")
    short, long = runs["short"], runs["long"]
    print(f"long / short ({long.frames} vs {short.frames} frames): peak RSS "
          f"{long.peak_rss_mib / short.peak_rss_mib:.3f} ({long.peak_rss_mib - short.peak_rss_mib:+.1f} MiB), "
          f"peak RSS from the early frame on {long.streaming_peak_rss_mib / short.streaming_peak_rss_mib:.3f} "
          f"({long.streaming_peak_rss_mib - short.streaming_peak_rss_mib:+.1f} MiB)")
    growth = long.rss_last_mib - long.rss_early_mib
    frames_between = long.frames - early_frame(long.frames)
    print(f"long video's RSS from frame {early_frame(long.frames)} to the last: {growth:+.1f} MiB "
          f"({growth * MIB / max(frames_between, 1):.0f} bytes per frame)")


def print_measuring_table(seconds: dict[str, float]) -> None:
    print(f"\n{'measuring (k-d tree)':20s} {'seconds':>8s}")
    for label, value in seconds.items():
        print(f"{label:20s} {value:8.1f}")
    print(f"scipy defaults / ours: {seconds['scipy defaults'] / seconds['ours']:.2f}x (same figures)")


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device, "--device")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {args.threads} threads"
    print(f"endoflow reconstruct on {device} ({name}); default model (latent bank on, untrained) at "
          f"{MODEL_SIZE} px")
    params = model_params()
    with tempfile.TemporaryDirectory(prefix="bench_reconstruct_") as tmp:
        work = Path(tmp)
        model_file = write_untrained_model_file(work / "endoflow.pt", params)
        speed = measure_speed(args, work, params, model_file) if "speed" in args.parts else []
        memory = measure_memory(args, work, params, model_file) if "memory" in args.parts else {}
        measuring = measure_measuring(args, work, params, model_file) if "measuring" in args.parts else {}
    if speed:
        print_speed_table(speed)
    if memory:
        print_memory_table(memory)
    if measuring:
        print_measuring_table(measuring)


if __name__ == "__main__":
    main()
