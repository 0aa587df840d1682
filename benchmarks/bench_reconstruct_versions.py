"""`reconstruct` of an earlier version of the code against this one, in one run: frames/s of the whole call.

    python benchmarks/bench_reconstruct_versions.py --baseline DIR [--frames 60] [--device cpu|cuda]
                                                    [--rounds 1] [--threads 2] [--cases video64 data480 ...]
                                                    [--video-frames 240]
                                                    [--versions before after] [--precision float32|bf16]
                                                    [--model FILE]

``DIR`` holds an earlier ``endoflow`` package (``git archive <commit> endoflow | tar -x -C DIR``); ``before`` runs
it, ``after`` this tree, each case in a fresh process with ``--threads`` torch threads. The inputs are made once by
the baseline's code (its model file is one both versions read): the default model (latent bank on, ``data.size``
64) randomly initialised and saved as a model file, or ``--model FILE`` (a trained one: its depth is a surface's,
which gives fusion and the tracker their real work; an untrained model's is nearly flat); sequence S1 of a synthetic
SimCol3D layout rendered at 480 px on ``--device`` (``--frames`` frames; the layout renders one sequence per scene,
S1, B1 and O1, in parallel); and, for the video case only, the same frames upscaled to 1920 x 1080 in an H.264 MP4
of ``--video-frames`` frames (the rendered ones forwards, then backwards, and again: a 1080p frame is cheap to
encode, a 480 px one dear to render). Cases (the whole ``reconstruct()`` call: model load, field of view, decoding,
inference, path refinement off unless a case says so, fusion, every output written; frames/s is frames over the
call's wall time, after an untimed 3-frame warm-up call; "per frame" is the rate of the frames a call of all of them
takes beyond one of the first half, without the start-up and the end of a call: model load, the field-of-view pass,
the contact sheet).
The field of view is found in a call's first 60 frames: where the first half is shorter, the longer call looks at
more of them, and each is read a second time inside the per-frame figure (a 1080p decode for the video, hence its
240 frames; a 480 px PNG for the sequence, with ``--frames`` under 120):

- ``video64``: the 1080p video at the model's 64 px, fused (decoding large frames on the critical path or not);
- ``data64``: the 480 px dataset sequence at 64 px, fused;
- ``data64-refined``: ``data64`` with the path refined (as ``data480-refined`` below), the built-in data's size;
- ``data480``: the dataset sequence at 480 px, fused (every fused case with the voxel :func:`far_footprint_cm` of
  the first frame's depth, the same in both versions);
- ``data480-nofusion``: the same without fusion;
- ``data480-refined``: ``data480`` with the path refined against keyframes (``refine`` of the default params, what
  ``endoflow reconstruct`` does unless told ``--no-refine``);
- ``core64``, ``core480``: the model and the fusion alone, as each version's ``reconstruct`` runs them (the earlier
  one frame by frame with its numpy TSDF; this one in batches of ``frames_per_call`` with the TSDF on the device),
  on frames decoded and resized beforehand, nothing written: what a GPU can be timed on where PyAV and rerun
  (the outputs' video and recording) are not installed. Per frame only (the start-up is left out).

``--versions after`` times this tree alone (the figures of ``before`` print as nan). ``--precision bf16`` runs this
tree's networks under bf16 autocast (``reconstruct --precision``); the earlier code runs float32, which is all it
had before the option: with ``--baseline`` an archive of this very commit, the two columns are float32 and bf16 of
one code. With ``--rounds`` > 1 the two versions alternate so that load from other processes hits both alike, and
the median is printed. Figures are printed, not asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from code_versions import environment_importing

if TYPE_CHECKING:  # each run imports the endoflow its version names, inside the functions
    from endoflow.config import Params

ROOT = Path(__file__).resolve().parents[1]
CASES = {"video64": ("video", 64, True, False), "data64": ("data", 64, True, False),
         "data64-refined": ("data", 64, True, True), "data480": ("data", 480, True, False),
         "data480-nofusion": ("data", 480, False, False), "data480-refined": ("data", 480, True, True),
         "core64": ("core", 64, True, False), "core480": ("core", 480, True, False)}  # kind, size, fused, path refined
VIDEO_SIZE = (1080, 1920)
WARM_UP_FRAMES = 3
VERSIONS = ("before", "after")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="folder holding the earlier endoflow package")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--video-frames", type=int, default=240,
                        help="frames of the 1080p video (at least twice the field-of-view pass's 60)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cases", nargs="+", choices=tuple(CASES), default=list(CASES))
    parser.add_argument("--versions", nargs="+", choices=VERSIONS, default=list(VERSIONS),
                        help="'after' alone where the earlier code is known to be slow (its numpy TSDF at 480 px)")
    parser.add_argument("--model", type=Path, default=None,
                        help="a trained model file to reconstruct with (default: the default model, untrained)")
    parser.add_argument("--precision", choices=("float32", "bf16"), default="float32",
                        help="the networks' arithmetic in this tree ('after'); the earlier code runs float32")
    parser.add_argument("--worker", nargs=3, metavar=("CASE", "WORK", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--make-inputs", type=Path, metavar="WORK", help=argparse.SUPPRESS)
    parser.add_argument("--with-video", action="store_true", help=argparse.SUPPRESS)
    return parser.parse_args()


def run_worker(args: argparse.Namespace) -> dict:
    """One case with whichever endoflow this process's PYTHONPATH names: frames/s of the timed call."""
    if CASES[args.worker[0]][0] == "core":
        return run_core(args)
    import numpy as np
    import torch

    from endoflow.config import Params
    from endoflow.reconstruction.frames import FrameRange, open_frames
    from endoflow.reconstruction.reconstruct import ReconstructOptions, reconstruct

    torch.set_num_threads(args.threads)
    case, work, out = args.worker[0], Path(args.worker[1]), Path(args.worker[2])
    kind, size, fuse, refined = CASES[case]
    source = (open_frames(work / "video.mp4", None, Params()) if kind == "video"
              else open_frames(work / "scene", "S1", Params()))
    K = getattr(source, "K", None)
    refine = None
    if refined:  # the earlier code may predate the tracker: imported only where a case asks for it
        from endoflow.geometry.direct_alignment import tracker_settings

        refine = tracker_settings(Params().refine)

    def call(frames: FrameRange, folder: Path, voxel_cm: Optional[float] = None) -> dict:
        options = ReconstructOptions(frames=frames, size=size, fuse=fuse, device=args.device, refine=refine,
                                     voxel_cm=voxel_cm, **precision_option(args))
        with open(os.devnull, "w") as nowhere, contextlib.redirect_stderr(nowhere):
            return reconstruct(source, K, work / "model.pt", folder, options)

    warm_up = call(FrameRange(stop=WARM_UP_FRAMES), out / "warm-up")
    voxel = far_footprint_cm(written_depth(out / "warm-up", 0), np.asarray(warm_up["K"])) if fuse else None
    timed = {}
    half = (args.video_frames if kind == "video" else args.frames) // 2
    for name, frames in (("half", FrameRange(stop=half)), ("all", FrameRange())):
        started = time.perf_counter()
        summary = call(frames, out / name, voxel)
        timed[name] = {"frames": summary["frames"], "seconds": time.perf_counter() - started}
    shutil.rmtree(out)
    return timed


def run_core(args: argparse.Namespace) -> dict:
    """A ``core`` case: depth, pose and fusion of every frame, timed after three frames of warm-up."""
    import numpy as np
    import torch

    from endoflow.config import Params
    from endoflow.data.crop import frame_region
    from endoflow.data.frame_encoding import resize_rgb
    from endoflow.devices import images_to_device, resolve_device
    from endoflow.geometry.pose import invert_pose
    from endoflow.models.endoflow_model import load_trained_model
    from endoflow.reconstruction import reconstruct as steps
    from endoflow.reconstruction.frames import FrameRange, open_frames
    from endoflow.reconstruction.fusion import TSDFVolume

    torch.set_num_threads(args.threads)
    _, size, _, _ = CASES[args.worker[0]]
    work = Path(args.worker[1])
    device = resolve_device(args.device, "--device")
    source = open_frames(work / "scene", "S1", Params())
    rgbs = [resize_rgb(frame.rgb, size) for frame in source.frames(FrameRange())]
    model, record = load_trained_model(work / "model.pt", device)
    region = frame_region(source.native_size, None, source.description)
    K, _ = steps.input_intrinsics(source.K, region, size, model, record.params.data.assumed_fov_deg)
    batched = hasattr(steps, "predict_frames")  # this version; the earlier one predicts frame by frame
    batch = steps.frames_per_call(size, device) if batched else 1
    arithmetic = contextlib.nullcontext()
    if batched:  # the networks' layout and arithmetic for frames of this size, as this version's reconstruct has them
        from endoflow.devices import autocast, to_compute_layout

        model = to_compute_layout(model, device, args.precision, size)
        arithmetic = autocast(device, args.precision)

    def fuse(frames: list) -> None:
        volume, pose, previous = None, np.eye(4), None
        with torch.no_grad():
            for start in range(0, len(frames), batch):
                chunk = frames[start:start + batch]
                images = images_to_device(torch.from_numpy(np.stack(chunk)).permute(0, 3, 1, 2).contiguous(),
                                          device, args.precision)
                if batched:
                    with arithmetic:
                        predicted = steps.predict_frames(model, images, previous, 1.0, work / "model.pt",
                                                         list(range(start, start + len(chunk))))
                else:
                    predicted = [steps.predict_frame(model, images, previous, 1.0, work / "model.pt", start)]
                for rgb, (depth, T_cur_prev) in zip(chunk, predicted):
                    pose = pose if T_cur_prev is None else pose @ invert_pose(T_cur_prev)
                    if volume is None:
                        voxel = far_footprint_cm(depth, K)
                        volume = TSDFVolume(voxel, 4 * voxel, device) if batched else TSDFVolume(voxel, 4 * voxel)
                    volume.integrate(depth, rgb, K, pose)
                previous = images[-1:]
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fuse(rgbs[:WARM_UP_FRAMES])
    timed = {}
    for name, frames in (("half", rgbs[:len(rgbs) // 2]), ("all", rgbs)):
        started = time.perf_counter()
        fuse(frames)
        timed[name] = {"frames": len(frames), "seconds": time.perf_counter() - started}
    return timed


def far_footprint_cm(depth_cm: "np.ndarray", K: "np.ndarray") -> float:
    """The voxel both versions fuse with: one pixel's footprint at the 95th percentile of the first frame's depth,
    the rule of this tree's ``reconstruct`` (``default_voxel_cm``, there on the float depth, here on the depth as
    written in 10 micrometre steps), which the earlier one may predate. (Before it
    followed the depth, the default was the footprint at 5 cm, where the untrained model sees everything at about 0.2
    cm: its surface then fused into a few voxels, and fusion looked cheap.)"""
    import numpy as np

    return float(np.quantile(depth_cm[depth_cm > 0], 0.95) / K[0, 0])


def written_depth(folder: Path, index: int) -> "np.ndarray":
    """Frame ``index``'s depth (cm) as a reconstruction in ``folder`` wrote it."""
    import cv2

    unit = json.loads((folder / "depth" / "depth.json").read_text())["unit_cm"]
    return cv2.imread(str(folder / "depth" / f"{index:06d}.png"), cv2.IMREAD_UNCHANGED) * unit


def precision_option(args: argparse.Namespace) -> dict:
    """``ReconstructOptions``' precision where it is not float32 (the earlier code has no such field)."""
    return {"precision": args.precision} if args.precision != "float32" else {}


def make_inputs(work: Path, frames: int, threads: int, video_frames: Optional[int], device: str) -> None:
    """The model file, the 480 px scene (rendered on ``device``: at 480 px a CPU renders about 0.6 frames/s a
    process) and, where ``video_frames`` is given, the 1080p video of that many frames (see the module docstring);
    each step says when it starts and ends, so that a run cut short by a time limit shows where it stood."""
    import numpy as np
    import torch

    from endoflow.config import Params
    from endoflow.models.endoflow_model import build_model
    from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
    from endoflow.synth.writers import synthesize_layout

    params = Params()
    torch.manual_seed(0)
    size = params.data.size
    baselines = TrainingBaselines(mean_depth_cm=7.0, mean_depth_map=np.full((size, size), 7.0, np.float32),
                                  mean_relative_pose=np.eye(4))
    save_model_file(work / "model.pt", ModelRecord(params=params, state=build_model(params, None).state_dict(),
                                                   epoch=0, val={}, mlflow_run_id=None, baselines=baselines))
    print(f"rendering {frames} frames a sequence at 480 px", file=sys.stderr, flush=True)
    print(synthesize_layout("simcol", work / "scene", sequences=1, frames=frames, size=480, seed=0, params=params,
                            workers=threads, device=device), file=sys.stderr, flush=True)
    if video_frames is not None:
        write_video(work, params, video_frames)


def write_video(work: Path, params: Params, count: int) -> None:
    """``count`` frames of the scene's, upscaled to 1920 x 1080, forwards then backwards and again, in an H.264 MP4
    (PyAV: only the video case needs it)."""
    import av
    import cv2

    from endoflow.reconstruction.frames import FrameRange, open_frames

    started = time.perf_counter()
    height, width = VIDEO_SIZE
    with av.open(str(work / "video.mp4"), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=25, options={"preset": "ultrafast"})
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        rendered = [frame.rgb for frame in open_frames(work / "scene", "S1", params).frames(FrameRange())]
        for index in ping_pong(len(rendered), count):
            large = cv2.resize(rendered[index], (width, height), interpolation=cv2.INTER_LINEAR)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(large, format="rgb24")))
        container.mux(stream.encode())
    print(f"1080p video of {count} frames encoded in {time.perf_counter() - started:.1f} s", file=sys.stderr,
          flush=True)


def ping_pong(length: int, count: int) -> list[int]:
    """``count`` positions in ``length`` frames, forwards to the last, backwards to the first, and again."""
    cycle = (list(range(length)) + list(range(length - 2, 0, -1))) or [0]
    return [cycle[i % len(cycle)] for i in range(count)]


def in_version(args: argparse.Namespace, version: str, arguments: list[str], progress: bool = False) -> str:
    """This script run with ``arguments`` in a fresh process importing ``version``'s endoflow; its output. Its
    messages pass through as they come where ``progress``, else they are shown only if it fails."""
    tree = args.baseline.resolve() if version == "before" else ROOT
    env = environment_importing(tree)
    command = [sys.executable, __file__, "--baseline", str(args.baseline), "--device", args.device,
               "--threads", str(args.threads), "--frames", str(args.frames), "--video-frames", str(args.video_frames),
               "--precision", args.precision if version == "after" else "float32", *arguments]
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, stderr=None if progress else subprocess.PIPE,
                          text=True)
    if done.returncode:
        detail = f":\n{done.stderr[-3000:]}" if done.stderr else " (its messages above)"
        raise SystemExit(f"{version} {' '.join(arguments)} failed{detail}")
    return done.stdout


def run_case(args: argparse.Namespace, version: str, case: str, work: Path) -> dict:
    output = in_version(args, version, ["--worker", case, str(work), str(work / f"out-{version}")])
    return json.loads(output.strip().splitlines()[-1])


def main() -> None:
    args = parse_args()
    if args.worker:
        print(json.dumps(run_worker(args)))
        return
    if args.make_inputs:
        make_inputs(args.make_inputs, args.frames, args.threads, args.video_frames if args.with_video else None,
                    args.device)
        return
    with tempfile.TemporaryDirectory(prefix="bench_reconstruct_versions_") as folder:
        work = Path(folder)
        started = time.perf_counter()
        video = any(CASES[case][0] == "video" for case in args.cases)
        in_version(args, "before", ["--make-inputs", str(work), *(["--with-video"] if video else [])], progress=True)
        if args.model is not None:
            shutil.copyfile(args.model, work / "model.pt")
        print(f"inputs made in {time.perf_counter() - started:.0f} s", flush=True)
        rates: dict[tuple[str, str, str], list[float]] = {}
        for round_index in range(args.rounds):
            for case in args.cases:
                for version in args.versions:
                    run = run_case(args, version, case, work)
                    whole = run["all"]["frames"] / run["all"]["seconds"]
                    extra = (run["all"]["frames"] - run["half"]["frames"]) / (run["all"]["seconds"]
                                                                              - run["half"]["seconds"])
                    rates.setdefault((case, version, "call"), []).append(whole)
                    rates.setdefault((case, version, "frame"), []).append(extra)
                    print(f"round {round_index + 1}/{args.rounds} {case:17s} {version:6s} {whole:7.2f} frames/s "
                          f"({extra:.2f} per frame)", flush=True)
    print(f"\nreconstruct, {args.frames} frames ({args.video_frames} in the video), {args.device}, {args.threads} "
          f"torch threads, {args.rounds} round(s); before: {args.baseline} (float32), after: this tree "
          f"({args.precision}); model: {args.model or 'the default, untrained'}")
    print(f"{'case':17s} {'before':>9s} {'after':>9s} {'after/before':>13s} {'per frame: before':>18s} "
          f"{'after':>9s} {'after/before':>13s}   (frames/s)")
    for case in args.cases:
        call, frame = ([statistics.median(rates[(case, v, kind)]) if v in args.versions else float("nan")
                        for v in VERSIONS] for kind in ("call", "frame"))
        print(f"{case:17s} {call[0]:9.2f} {call[1]:9.2f} {call[1] / call[0]:13.2f} {frame[0]:18.2f} "
              f"{frame[1]:9.2f} {frame[1] / frame[0]:13.2f}")


if __name__ == "__main__":
    main()
