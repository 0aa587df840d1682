"""Write procedural data in the native layouts of SimCol3D, EndoSLAM (UnityCam) and SceneNet RGB-D, and as
unlabelled video (:mod:`endoflow.data.video`).

The bytes follow docs/datasets.md with the readers' own format constants, so our readers read synthetic and
real data alike. Each sequence is staged and swapped in whole, and its bytes do not depend on the number of
worker processes. See docs/synthetic_data.md, "What is written".
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator, Optional

import cv2
import numpy as np
import torch

from endoflow.config import ConfigError, Params, SimColConfig
from endoflow.config import SYNTH_LAYOUTS
from endoflow.data.endoslam import UNITYCAM_COLUMNS, UNITYCAM_K, UNITYCAM_POSE_SUFFIX, UNITYCAM_SIZE
from endoflow.data.imageio import write_png
from endoflow.data.scenenet import scenenet_intrinsics
from endoflow.data.simcol import DEPTH_COUNTS_PER_CM as SIMCOL_DEPTH_COUNTS_PER_CM
from endoflow.data.simcol import SCENES as SIMCOL_SCENE_FOLDERS
from endoflow.data.simcol import parse_cam_txt
from endoflow.data.video_encoding import write_video
from endoflow.devices import resolve_device
from endoflow.geometry.camera import scale_intrinsics
from endoflow.geometry.pose import matrix_to_quaternion_xyzw, opencv_to_unity
from endoflow.io import files_only, staged_directory, write_text
from endoflow.synth.render import MAX_DEPTH_CM, render_tube_frame
from endoflow.synth.rooms import Room, camera_path, make_room, render_room
from endoflow.synth.scenes import (
    SECOND_LOOK_CIRCLE,
    SECOND_LOOK_FOCAL,
    STYLES,
    TubeSequence,
    make_tube_sequence,
    second_look,
)

SIMCOL_SCENES = tuple(zip(SIMCOL_SCENE_FOLDERS, ("S", "B", "O")))  # scene folder, sequence letter
SIMCOL_SCENE_III_SEQUENCES = 3
SIMCOL_CAM_TXT = "227.60416 0 227.60416 0 237.5 237.5 0 0 1"  # byte-identical to the real file
SIMCOL_ALPHA = 65280
UNITYCAM_ORGANS = (("Colon", "colon"), ("Small Intestine", "intestine"), ("Stomach", "stomach"))
SCENENET_FRAME_STEP = 25
SCENENET_VAL_EVERY = 10
SCENENET_JPEG_QUALITY = 90
VIDEO_FPS = 30.0
# the circle an endoscope's image is, as a share of the frame's side: its corners are black, its sides touch
VIDEO_CIRCLE_DIAMETER = 1.1
# what a sequence folder holds once rendered: a rerun replaces it, a folder with anything else is refused
RENDERED_SEQUENCE = files_only("a rendered sequence (PNG, JPEG, CSV and text files)",
                               ("*.png", "*.jpg", "*.csv", "*.txt"))


@dataclass(frozen=True)
class Job:
    """One sequence to render; plain data so that it can be sent to a worker process."""

    layout: str
    group: str  # SimCol scene folder, UnityCam organ, SceneNet split
    name: str  # SimCol sequence (S1), organ file stem (colon), SceneNet trajectory
    target: str  # the folder that holds the finished sequence
    frames: int
    scripted: bool  # a test sequence: its camera follows camera_path.TEST_SCRIPT
    size: int
    entropy: tuple[int, ...]
    device: str
    endoslam_depth_full_scale_cm: float
    endoslam_translation_to_cm: float
    endoslam_fps: float
    look: str = "built-in"  # synth.look
    phase_frames: Optional[tuple[int, int]] = None  # synth.phase_frames (None: the style's); scripts ignore it


@dataclass(frozen=True)
class LayoutPlan:
    """What one layout's rendering writes: its sequences as jobs, under dataset root ``out``."""

    layout: str
    out: Path
    jobs: tuple[Job, ...]
    size: int
    workers: int
    device: str
    cam_txt: Optional[str] = None  # the cam.txt every SimCol scene folder holds (simcol only)

    @property
    def frames(self) -> int:
        return sum(job.frames for job in self.jobs)

    def summary(self) -> str:
        return (f"{self.layout}: {len(self.jobs)} sequences, {self.frames} frames at "
                f"{_frame_size(self.layout, self.size)} written to {self.out}")


def synthesize_layout(layout: str, out: Path, *args: Any, **settings: Any) -> str:
    """Render ``layout`` into dataset root ``out`` as :func:`plan_layout` plans it (same arguments); returns a
    summary."""
    plan = plan_layout(layout, out, *args, **settings)
    seconds = render_plans([plan])
    return f"{plan.summary()} in {render_pace(plan.frames, seconds, plan)}"


def synthesize_layouts(outs: dict[str, Path], params: Params) -> list[str]:
    """Render every layout of ``outs`` (layout -> dataset root) with ``params.synth``'s settings, all sequences in
    one pool of worker processes; returns a line per layout and one for the whole rendering. The bytes are those
    of :func:`synthesize_layout` for each layout alone."""
    plans = [plan_layout(layout, out, params=params) for layout, out in outs.items()]
    seconds = render_plans(plans)
    frames = sum(plan.frames for plan in plans)
    total = f"{frames} frames rendered in {render_pace(frames, seconds, plans[0])}"
    return [plan.summary() for plan in plans] + [total]


def render_pace(frames: int, seconds: float, plan: LayoutPlan) -> str:
    """How long ``frames`` took, and with what (the summary lines' ending)."""
    return f"{seconds:.1f} s ({frames / seconds:.1f} frames/s, {plan.workers} workers, device {plan.device})"


def plan_layout(
    layout: str,
    out: Path,
    sequences: Optional[int] = None,
    frames: Optional[int] = None,
    size: Optional[int] = None,
    seed: Optional[int] = None,
    *,
    test_frames: Optional[int] = None,
    params: Optional[Params] = None,
    workers: Optional[int] = None,
    device: Optional[str] = None,
) -> LayoutPlan:
    """What rendering ``layout`` (``simcol``, ``endoslam``, ``scenenet``, ``video``) into dataset root ``out``
    writes, planned; nothing is written yet.

    ``None`` arguments take ``params.synth`` defaults (``Params()`` when ``params`` is None): sequences per
    scene / organ count / trajectories, frames per sequence, frames per test sequence (``frames`` given alone
    sets both), square image size, seed, worker processes, device name (as ``synth.device``: ``auto``, ``cpu``,
    ``cuda`` or ``cuda:N``). Test sequences (``data.simcol.test``; every EndoSLAM sequence when
    ``data.endoslam.split`` is test) follow the test script of :mod:`endoflow.synth.camera_path`. The EndoSLAM depth scale,
    pose unit and frame rate come from ``params.data.endoslam``, so that the reader decodes what was written.
    Same arguments, same bytes.
    """
    if layout not in SYNTH_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {', '.join(SYNTH_LAYOUTS)}")
    params = params or Params()
    defaults = getattr(params.synth, layout)
    sequences = defaults.sequences if sequences is None else sequences
    if test_frames is None:
        test_frames = frames if frames is not None else getattr(defaults, "test_frames", None) or defaults.frames
    frames = defaults.frames if frames is None else frames
    size = params.synth.size if size is None else size
    seed = params.synth.seed if seed is None else seed
    device = str(resolve_device(params.synth.device if device is None else device, "synth.device"))
    workers = params.synth.workers if workers is None else workers
    if sequences < 1 or min(frames, test_frames) < 2 or size < 8:
        raise ValueError(f"need sequences >= 1, frames and test frames >= 2, size >= 8; got {sequences}, {frames}, "
                         f"{test_frames}, {size}")
    out = Path(out)
    jobs = plan_jobs(layout, out, sequences, frames, size, seed, device, params, test_frames)
    cam_txt = simcol_cam_txt(params.synth.look) if layout == "simcol" else None
    return LayoutPlan(layout, out, tuple(jobs), size, workers, device, cam_txt)


def render_plans(plans: list[LayoutPlan]) -> float:
    """Write what ``plans`` plan, every sequence of them in one pool of worker processes (spawned, each importing
    torch once: one pool per stage, not per layout) where the first plan asks for several on a CPU; returns the
    seconds the rendering took."""
    for plan in plans:
        plan.out.mkdir(parents=True, exist_ok=True)
        if plan.cam_txt is not None:
            for scene in sorted({job.group for job in plan.jobs}):
                write_text(plan.out / scene / "cam.txt", plan.cam_txt)
    jobs = [job for plan in plans for job in plan.jobs]
    workers, device = plans[0].workers, plans[0].device
    started = time.perf_counter()
    if workers > 1 and len(jobs) > 1 and torch.device(device).type == "cpu":
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context) as pool:
            list(pool.map(render_job, jobs))
    else:
        for job in jobs:
            render_job(job)
    return time.perf_counter() - started


def _frame_size(layout: str, size: int) -> str:
    height, width = scenenet_shape(size) if layout == "scenenet" else (size, size)
    return f"{width}x{height}"


def plan_jobs(layout: str, out: Path, sequences: int, frames: int, size: int, seed: int, device: str, params: Params,
              test_frames: Optional[int] = None) -> list[Job]:
    """The sequences a call of :func:`synthesize_layout` renders, in order; a test sequence has ``test_frames``
    (``None``: ``frames``)."""
    def length(test: bool) -> dict:
        return {"frames": (test_frames or frames) if test else frames, "scripted": test}

    common = dict(
        size=size,
        device=device,
        endoslam_depth_full_scale_cm=params.data.endoslam.depth_full_scale_cm,
        endoslam_translation_to_cm=params.data.endoslam.unitycam_translation_to_cm,
        endoslam_fps=params.data.endoslam.fps,
        look=params.synth.look,
        phase_frames=None if params.synth.phase_frames is None else (params.synth.phase_frames[0],
                                                                     params.synth.phase_frames[1]),
    )
    layout_id = SYNTH_LAYOUTS.index(layout)
    jobs = []
    if layout == "simcol":
        for scene_id, (scene, letter) in enumerate(SIMCOL_SCENES):
            count = min(sequences, SIMCOL_SCENE_III_SEQUENCES) if scene.endswith("_III") else sequences
            for i in range(1, count + 1):
                name = f"{letter}{i}"
                target = out / scene / f"Frames_{name}"
                jobs.append(Job("simcol", scene, name, str(target), entropy=(seed, layout_id, scene_id, i),
                                **length(name in params.data.simcol.test), **common))
    elif layout == "endoslam":
        if sequences > len(UNITYCAM_ORGANS):
            raise ConfigError(f"synth.endoslam.sequences must be at most {len(UNITYCAM_ORGANS)} (one sequence per "
                              f"UnityCam organ), got {sequences}")
        for organ_id, (organ, stem) in enumerate(UNITYCAM_ORGANS[:sequences]):
            target = out / "UnityCam" / organ
            jobs.append(Job("endoslam", organ, stem, str(target), entropy=(seed, layout_id, organ_id),
                            **length(params.data.endoslam.split == "test"), **common))
    elif layout == "video":
        styles = sorted(STYLES)
        for i in range(sequences):
            # a video file, then a folder of frames, in turn
            target = out / (f"clip_{i:03d}.mp4" if i % 2 == 0 else f"clip_{i:03d}")
            jobs.append(Job("video", styles[i % len(styles)], f"clip_{i:03d}", str(target),
                            entropy=(seed, layout_id, i), **length(False), **common))
    else:
        for i in range(sequences):
            split = "val" if i % SCENENET_VAL_EVERY == SCENENET_VAL_EVERY - 1 else "train"
            target = out / split / "0" / str(i)
            jobs.append(Job("scenenet", split, str(i), str(target), entropy=(seed, layout_id, i), **length(False),
                            **common))
    return jobs


def render_job(job: Job) -> None:
    """Render one sequence into a temporary folder and swap it into place (runs in worker processes)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # same arithmetic, hence same bytes, in any process layout
    try:
        target = Path(job.target)
        if job.layout == "video" and target.suffix == ".mp4":
            write_video(target, video_frames(job), VIDEO_FPS)
            return
        writer = {"simcol": _write_simcol, "endoslam": _write_endoslam, "scenenet": _write_scenenet,
                  "video": _write_video_folder}[job.layout]
        with staged_directory(target, RENDERED_SEQUENCE) as staging:
            extra_files = writer(job, staging)
            # Files that live beside the sequence folder (SimCol's pose files) go first, before the folder
            # swap: readers list sequences by their frame folders, so a pose file without frames is never read.
            for name in extra_files:
                os.replace(staging / name, target.parent / name)
    finally:
        torch.set_num_threads(threads)


def job_rng(job: Job) -> np.random.Generator:
    """The random stream of one sequence: depends on the seed, layout and sequence only."""
    return np.random.default_rng(np.random.SeedSequence(list(job.entropy)))


def tube_sequence(job: Job) -> TubeSequence:
    """The scene and camera poses of a SimCol, EndoSLAM or video job (what its files are rendered from), in its look,
    its camera's phases lasting ``job.phase_frames`` where that is set."""
    style = STYLES[job.group] if job.look == "built-in" else second_look(STYLES[job.group])
    if job.phase_frames is not None:
        style = replace(style, motion=replace(style.motion, phase_frames=job.phase_frames))
    return make_tube_sequence(style, job.frames, job_rng(job), torch.device(job.device), job.scripted)


def in_view(rgb: np.ndarray, look: str) -> np.ndarray:
    """``rgb`` (``H x W x 3`` float) as the look's camera sees it: the second look's circle, black outside."""
    if look == "built-in":
        return rgb
    return rgb * circle(rgb.shape[0], rgb.shape[1], SECOND_LOOK_CIRCLE)[..., None]


def circle(height: int, width: int, diameter: float) -> np.ndarray:
    """``H x W`` bool: a centred circle ``diameter`` times the frame's shorter side across."""
    v, u = np.mgrid[:height, :width]
    radius = diameter * min(height, width) / 2
    return (u - (width - 1) / 2) ** 2 + (v - (height - 1) / 2) ** 2 <= radius**2


# -------------------------------------------------------------------------------------------- SimCol3D
def simcol_cam_txt(look: str = "built-in") -> str:
    """``cam.txt``: the real file's bytes, or in the second look its focal lengths shortened."""
    if look == "built-in":
        return SIMCOL_CAM_TXT
    K = parse_cam_txt(SIMCOL_CAM_TXT, "cam.txt")
    K[0, 0] *= SECOND_LOOK_FOCAL
    K[1, 1] *= SECOND_LOOK_FOCAL
    return " ".join(f"{value:.9g}" for value in K.ravel())


def simcol_intrinsics(size: int, look: str = "built-in") -> np.ndarray:
    """The K our SimCol reader derives for ``size``-px frames: ``cam.txt`` scaled from its reference size."""
    K = parse_cam_txt(simcol_cam_txt(look), "cam.txt")
    scale = size / SimColConfig().reference_size
    return scale_intrinsics(K, scale, scale)


def _write_simcol(job: Job, staging: Path) -> list[str]:
    sequence = tube_sequence(job)
    K = simcol_intrinsics(job.size, job.look)
    for f, pose in enumerate(sequence.poses):
        rgb, depth = render_tube_frame(sequence.scene, pose, K, job.size, job.size)
        write_png(staging / f"FrameBuffer_{f:04d}.png", simcol_frame(in_view(rgb, job.look)))
        write_png(staging / f"Depth_{f:04d}.png", simcol_depth(depth))
    unity = opencv_to_unity(sequence.poses)
    positions = f"SavedPosition_{job.name}.txt"
    rotations = f"SavedRotationQuaternion_{job.name}.txt"
    _write_rows(staging / positions, unity[:, :3, 3], " ")
    _write_rows(staging / rotations, matrix_to_quaternion_xyzw(unity[:, :3, :3]), " ")
    return [positions, rotations]


def simcol_frame(rgb: np.ndarray) -> np.ndarray:
    """SimCol FrameBuffer pixels: ``H x W x 4`` uint16 RGBA, 8-bit values times 256, alpha 65280."""
    values = to_uint8(rgb).astype(np.uint16) * 256
    alpha = np.full(rgb.shape[:2] + (1,), SIMCOL_ALPHA, dtype=np.uint16)
    return np.concatenate([values, alpha], axis=-1)


def simcol_depth(depth_cm: np.ndarray) -> np.ndarray:
    """SimCol depth counts (uint16, ``cm = value / 255 / 256 * 20``), refusing depths beyond the scale."""
    if not np.isfinite(depth_cm).all() or depth_cm.max() > MAX_DEPTH_CM:
        raise ValueError(f"depth outside SimCol's 0..20 cm scale (max {np.nanmax(depth_cm):.3f} cm)")
    return np.round(depth_cm.astype(np.float64) * SIMCOL_DEPTH_COUNTS_PER_CM).clip(0, 65535).astype(np.uint16)


# ---------------------------------------------------------------------------------- EndoSLAM UnityCam
def unitycam_intrinsics(size: int) -> np.ndarray:
    """The K our EndoSLAM reader derives for ``size``-px UnityCam frames (documented K scaled from 320)."""
    height, width = UNITYCAM_SIZE
    return scale_intrinsics(UNITYCAM_K, size / width, size / height)


def _write_endoslam(job: Job, staging: Path) -> list[str]:
    sequence = tube_sequence(job)
    K = unitycam_intrinsics(job.size)
    for sub in ("Frames", "Pixelwise Depths", "Poses"):
        (staging / sub).mkdir()
    for f, pose in enumerate(sequence.poses):
        rgb, depth = render_tube_frame(sequence.scene, pose, K, job.size, job.size)
        write_png(staging / "Frames" / f"image_{f:04d}.png", to_uint8(in_view(rgb, job.look)))
        write_png(staging / "Pixelwise Depths" / f"aov_image_{f:04d}.png", unitycam_depth(depth, job.endoslam_depth_full_scale_cm))
    unity = opencv_to_unity(sequence.poses)
    times = np.arange(job.frames) / job.endoslam_fps
    rows = np.concatenate(
        [unity[:, :3, 3] / job.endoslam_translation_to_cm, matrix_to_quaternion_xyzw(unity[:, :3, :3]), times[:, None]],
        axis=1,
    )
    _write_rows(staging / "Poses" / f"{job.name}{UNITYCAM_POSE_SUFFIX}", rows, ",", header=",".join(UNITYCAM_COLUMNS))
    return []


def unitycam_depth(depth_cm: np.ndarray, full_scale_cm: float) -> np.ndarray:
    """UnityCam depth pixels: ``H x W x 4`` uint8 RGBA with equal colour channels, ``cm = value / 255 * scale``."""
    if depth_cm.max() > full_scale_cm:
        raise ValueError(f"depth {depth_cm.max():.3f} cm beyond data.endoslam.depth_full_scale_cm = {full_scale_cm}")
    value = np.round(depth_cm / full_scale_cm * 255).astype(np.uint8)
    return np.stack([value, value, value, np.full_like(value, 255)], axis=-1)


# ---------------------------------------------------------------------------------------------- video
def video_frames(job: Job) -> Iterator[np.ndarray]:
    """The frames of a video job: a tube sequence rendered with SimCol's camera, seen through a circle (black
    corners, as an endoscope's image); no depth, no poses are written."""
    sequence = tube_sequence(job)
    K = simcol_intrinsics(job.size, job.look)
    inside = circle(job.size, job.size, VIDEO_CIRCLE_DIAMETER)[..., None]
    for pose in sequence.poses:
        rgb, _ = render_tube_frame(sequence.scene, pose, K, job.size, job.size)
        yield to_uint8(rgb) * inside.astype(np.uint8)


def _write_video_folder(job: Job, staging: Path) -> list[str]:
    """A folder of frames, and beside it the camera's intrinsics (``<name>.intrinsics.yaml``, native pixels)."""
    for f, rgb in enumerate(video_frames(job)):
        write_png(staging / f"frame_{f:04d}.png", rgb)
    fx, fy, cx, cy = (float(v) for v in simcol_intrinsics(job.size, job.look)[[0, 1, 0, 1], [0, 1, 2, 2]])
    (staging / f"{job.name}.intrinsics.yaml").write_text(
        f"fx: {fx!r}\nfy: {fy!r}\ncx: {cx!r}\ncy: {cy!r}\nwidth: {job.size}\nheight: {job.size}\n")
    return [f"{job.name}.intrinsics.yaml"]


# ------------------------------------------------------------------------------------------ SceneNet
def room_sequence(job: Job) -> tuple[Room, np.ndarray]:
    """The room and camera poses ``[F, 4, 4]`` of a SceneNet job."""
    rng = job_rng(job)
    poses = camera_path(job.frames, rng)
    return make_room(rng, poses[:, :3, 3]), poses


def scenenet_shape(size: int) -> tuple[int, int]:
    """``(height, width)`` of SceneNet frames for ``size`` (128 gives the native 240 x 320)."""
    width = max(8, int(round(320 * size / 128 / 4)) * 4)
    return width * 3 // 4, width


def _write_scenenet(job: Job, staging: Path) -> list[str]:
    height, width = scenenet_shape(job.size)
    K = scenenet_intrinsics(height, width)
    room, poses = room_sequence(job)
    (staging / "photo").mkdir()
    (staging / "depth").mkdir()
    for f, pose in enumerate(poses):
        rgb, length_cm = render_room(room, pose, K, height, width, torch.device(job.device))
        n = f * SCENENET_FRAME_STEP
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(to_uint8(rgb), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, SCENENET_JPEG_QUALITY])
        if not ok:
            raise RuntimeError(f"OpenCV could not encode photo {n}")
        (staging / "photo" / f"{n}.jpg").write_bytes(jpeg.tobytes())
        write_png(staging / "depth" / f"{n}.png", np.round(length_cm * 10).clip(1, 65535).astype(np.uint16))
    return []


# ------------------------------------------------------------------------------------------- helpers
def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Float RGB in [0, 1] to uint8 (rounded)."""
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _write_rows(path: Path, rows: np.ndarray, separator: str, header: Optional[str] = None) -> None:
    lines = [header] if header else []
    lines += [separator.join(f"{value:.9g}" for value in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")

