"""``endoflow reconstruct``: depth per frame, the camera path and a fused surface from a trained model.

Frames stream through the model in small batches (:func:`frames_per_call`; centre-cropped and resized as
preprocessing does, K following, a batch ahead in a thread, :mod:`endoflow.reconstruction.streams`): each frame's
depth and the pose network's step from the previous frame, chained into camera-to-world poses from
the identity at the first frame (``T_world_cur = T_world_prev @ inv(T_cur_prev)``), then refined against
keyframes with the depth (:mod:`endoflow.geometry.direct_alignment`, unless ``refine`` is None) and their
orientations smoothed over a window of frames (:mod:`endoflow.geometry.path_smoothing`); the depth is fused along
the path. The outputs go into a staged folder that replaces ``out_dir`` whole, only where it is new, empty or an
earlier reconstruction (:func:`endoflow.io.check_replaceable`). What is written and what it means:
docs/reconstruction.md.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import shutil
import sys
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Optional, TypeVar

import numpy as np
import torch

from endoflow.config import DATASETS, PRECISIONS, ModelConfig, Params, Precision, ReconstructConfig
from endoflow.data.field_of_view import FIELD_OF_VIEW_FRAMES, NoFieldOfView, field_of_view, resized_field_of_view
from endoflow.data.frame_encoding import depth_to_counts, encode_png, resize_depth, resize_rgb, stored_intrinsics
from endoflow.devices import (autocast, compute_dtype, images_to_device, resolve_device, to_compute_layout,
                              unit_float_images)
from endoflow.errors import DataFormatError
from endoflow.geometry.direct_alignment import KeyframeTracker, TrackerSettings
from endoflow.geometry.path_smoothing import OrientationSmoother
from endoflow.geometry.pose import chain_step, invert_pose, relative_pose
from endoflow.io import check_replaceable, marked_output, staged_directory, write_bytes, write_json
from endoflow.losses.photometric import view_synthesis_error
from endoflow.models.depth_range import at_depth_range_ends, collapsed_depth_warning
from endoflow.models.endoflow_model import EndoflowModel, load_trained_model
from endoflow.progress import Progress, format_duration
from endoflow.reconstruction.alignment import ground_truth_in_path_world
from endoflow.data.crop import Crop, crop_intrinsics, crop_warning, frame_region, model_view
from endoflow.data.intrinsics import assumed_intrinsics
from endoflow.reconstruction.frames import FrameRange, FrameSource, InputFrame
from endoflow.reconstruction.fusion import SurfaceMesh, TSDFVolume, write_ply
from endoflow.reconstruction.pictures import FrameSampler, SideBySideVideo, depth_preview, write_contact_sheet
from endoflow.reconstruction.recording import RECORDING_FILE, Recording
from endoflow.reconstruction.streams import READ_AHEAD, Deferred, Encoders, WriteBehind, decoded_ahead, side_threads

if TYPE_CHECKING:  # MLflow takes seconds to import: only runs that log pay for it
    from endoflow.tracking import RunHandle

NETWORK_PATH_FILE = "trajectory_network.tum"  # the pose network's own chain, beside a refined trajectory.tum
ADAPTED_MODEL = "model_adapted.pt"  # with `reconstruct --adapt`: the model fitted to the input first
# What MLflow gets of a reconstruction: what a person opens first, the path and the surface (not the depth maps).
LOGGED_OUTPUTS = ("sheet.png", "video.mp4", RECORDING_FILE, "reconstruction.json", "trajectory.tum",
                  "trajectory.kitti", "trajectory.kitti.json", "mesh.ply")
DEPTH_UNIT_CM = 0.001  # 16-bit counts of 10 micrometres: up to 65.5 cm
# The paths PathPhotometry compares, and how many frames' errors it keeps on the device before reading them back:
# one wait for a GPU every so many frames, not one a frame, and a long video's errors leave the device as they come
PHOTOMETRY_PATHS = ("path", "network", "constant_velocity")
PHOTOMETRY_READ_FRAMES = 256
NETWORK_STRIDE = 32  # the encoders halve the image five times
# Frames per network call (frames_per_call): a GPU takes many at any size; a CPU gains from batching only while a
# batch's maps stay small (measured on 2 cores: 64 px gains 3.6x at 8, 480 px loses at 4).
GPU_BATCH = 16
CPU_BATCH_PIXELS = 8 * 64 * 64
CPU_MAX_BATCH = 8
Item = TypeVar("Item")
# reconstruction.json's "format": what tells an earlier reconstruction, which a run may replace, from any other
# folder, which it refuses to empty
RECONSTRUCTION_FORMAT = "endoflow reconstruction 1"
FORCE_OPTION = "--force"  # how a user replaces a folder that is not an earlier reconstruction
EARLIER_RECONSTRUCTION = marked_output(f"an earlier endoflow reconstruction (its reconstruction.json's format "
                                       f"{RECONSTRUCTION_FORMAT!r})", "reconstruction.json",
                                       format=RECONSTRUCTION_FORMAT)


@dataclass(frozen=True)
class ReconstructOptions:
    """``size``: square model input in px (None: the model's ``data.size``); ``scale``: factor on depth and path;
    ``voxel_cm``/``trunc_cm``: TSDF voxel and truncation in the depth's unit (None: from the first frame's depth,
    :func:`default_voxel_cm`; 4 voxels);
    ``npy``: also write float32 depth; ``fuse``: build the surface; ``device``: ``auto``, ``cpu`` or ``cuda``;
    ``force``: replace an output folder that holds something other than an earlier reconstruction; ``crop``: the
    region of the frames to use (None: all of it; see :mod:`endoflow.data.crop`); ``refine``: the
    tracker that refines the pose network's path against keyframes (None: the network's chain as it is);
    ``precision``: the networks' arithmetic (``reconstruct.precision`` in params)."""

    frames: FrameRange = field(default_factory=FrameRange)
    size: Optional[int] = None
    scale: float = 1.0
    voxel_cm: Optional[float] = None
    trunc_cm: Optional[float] = None
    npy: bool = False
    fuse: bool = True
    device: str = "auto"
    force: bool = False
    crop: Optional[Crop] = None
    refine: Optional[TrackerSettings] = None
    precision: Precision = ReconstructConfig.model_fields["precision"].default

    def __post_init__(self) -> None:
        if self.size is not None and (self.size < NETWORK_STRIDE or self.size % NETWORK_STRIDE):
            raise ValueError(f"--size must be a positive multiple of {NETWORK_STRIDE}, got {self.size}")
        for option, value in (("--scale", self.scale), ("--voxel-cm", self.voxel_cm), ("--trunc-cm", self.trunc_cm)):
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{option} must be a positive number, got {value}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"--precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")


@dataclass(frozen=True)
class Adaptation:
    """The model fitted to the input before it is reconstructed (``endoflow adapt``): the fitted model file (in a
    scratch folder), its steps, the held-out photometric error before and after, and whether it was kept (it
    explains the held-out frames better) and so reconstructs."""

    model: Path
    steps: int
    held_out_before: float
    held_out_after: float
    kept: bool

    @classmethod
    def of(cls, model: Path, summary: dict, kept: bool) -> "Adaptation":
        """From the summary ``endoflow.training.adapt.adapt`` returns."""
        return cls(model, summary["steps"], summary["held_out_photometric_before"],
                   summary["held_out_photometric_after"], kept)

    def record(self) -> dict:
        """What ``reconstruction.json`` says of it (an error that is not a finite number as null: JSON has none)."""
        return {"steps": self.steps, "held_out_photometric_before": finite_or_none(self.held_out_before),
                "held_out_photometric_after": finite_or_none(self.held_out_after), "kept": self.kept}


def finite_or_none(value: float) -> Optional[float]:
    return value if math.isfinite(value) else None


def reconstruct(source: FrameSource, K_native: Optional[np.ndarray], model_path: Path, out_dir: Path,
                options: ReconstructOptions, resume_key: Optional[str] = None,
                adaptation: Optional[Adaptation] = None) -> dict:
    """Run the model over ``source`` and write the outputs listed in the module docstring; returns the summary
    written to ``reconstruction.json``. ``K_native`` None: the intrinsics are unknown (:func:`input_intrinsics`).
    ``resume_key``, where given, is recorded in the summary: what a run over many videos keeps a folder by
    (:mod:`endoflow.reconstruction.many`). ``model_path`` is the model as trained; ``adaptation``, a fit of it made
    first, is recorded in the summary, and where it was kept its model reconstructs and is written into the output
    as :data:`ADAPTED_MODEL` (the model as trained stays one of the inputs the output may not replace)."""
    check_frame_range(source, options.frames)
    device = resolve_device(options.device, "--device")
    used = adaptation.model if uses_fitted_model(adaptation) else model_path
    model, record = load_trained_model(used, device)
    size = options.size or record.params.data.size
    model = to_compute_layout(model, device, options.precision, size)
    region = frame_region(source.native_size, options.crop, source.description)
    K, intrinsics_from = input_intrinsics(K_native, region, size, model, record.params.data.assumed_fov_deg)
    print(f"[reconstruct] intrinsics: {intrinsics_from}", file=sys.stderr)
    warning = crop_warning(source.native_size, region, source.description)
    if warning:
        print(f"[reconstruct] warning: {warning}", file=sys.stderr)
    max_depth = record.params.model.max_depth * options.scale
    unit = DEPTH_UNIT_CM * max(1, math.ceil(max_depth / (DEPTH_UNIT_CM * np.iinfo(np.uint16).max)))
    volume: Optional[TSDFVolume] = None  # made at the first frame: its voxel follows that frame's depth
    valid = input_field_of_view(source, options.frames, region, size)
    path = CameraPath()
    tracker = KeyframeTracker(torch.from_numpy(K), options.refine) if options.refine is not None else None
    # the tracker's path goes on from the poses as aligned; the path written has their orientations smoothed, which
    # holds each frame back until the frames its window reaches have been aligned
    network_chain, aligned_chain = Chain(), Chain()
    depth_scales: list[float] = []  # per frame, the tracker's factor on its depth (refine.depth_scale)
    smoother: OrientationSmoother[TrackedFrame] = OrientationSmoother(
        options.refine.rotation_smoothing if options.refine is not None else 0.0)
    explained = PathPhotometry(K, record.baselines.mean_relative_pose, options.frames.stride, options.scale, device)
    range_ends = RangeEndShare(record.params.model)
    progress = Progress(source_frame_count(source, options.frames), "frames")
    sampler = FrameSampler()
    with staged_directory(out_dir, EARLIER_RECONSTRUCTION, options.force, read_inputs(source, model_path),
                          FORCE_OPTION) as stage, torch.no_grad():
        recording = Recording(stage / RECORDING_FILE, source.description)
        with SideBySideVideo(stage / "video.mp4", source.fps / options.frames.stride, size, size) as video, \
                WriteBehind() as writes, Encoders() as encoders, contextlib.ExitStack() as stack:
            previous: Optional[torch.Tensor] = None
            shown: Optional[tuple[float, float]] = None
            per_call = frames_per_call(size, device)
            inputs = stack.enter_context(contextlib.closing(
                decoded_ahead(model_inputs(source, options.frames, region, size), per_call + READ_AHEAD,
                              side_threads())))

            def settle(tracked: TrackedFrame, pose: np.ndarray) -> None:
                """Everything that follows from a frame's pose on the path written, in frame order."""
                nonlocal shown, volume
                frame, rgb, depth = tracked.frame, tracked.frame.rgb, tracked.depth
                path.add(frame, pose, tracked.network_pose, depth, size)
                explained.add(rgb, depth, path)
                shown = shown or preview_range(depth, record.params.model, options.scale)
                preview = encoders.submit(write_depth, stage, frame.index, depth, unit, options.npy, shown)
                writes.submit(write_frame_outputs, frame.index, rgb, depth, pose, preview,
                              FrameOutputs(unit, K, video, recording, sampler))
                if options.fuse:
                    if volume is None:
                        volume = fusion_volume(depth, K, options, device)
                    volume.integrate(depth, rgb, K, pose)
                report_progress(path.count, progress)

            for batch in in_batches(inputs, per_call):
                images = images_to_device(torch.from_numpy(np.stack([rgb for _, rgb in batch])).permute(0, 3, 1, 2)
                                          .contiguous(), device, options.precision)
                with autocast(device, options.precision):
                    predicted = predict_frames(model, images, previous, options.scale, used,
                                               [frame.index for frame, _ in batch])
                for (frame, rgb), (depth, T_cur_prev) in zip(batch, predicted):
                    depth = np.where(valid, depth, np.float32(0))  # outside the field of view: unknown
                    range_ends.add(depth / options.scale, valid)
                    network_pose = network_chain.step(T_cur_prev, options.scale)
                    aligned = network_pose
                    if tracker is not None:
                        aligned_chain.end = aligned = tracker.track(
                            unit_float_images(torch.from_numpy(rgb).to(device).permute(2, 0, 1)),
                            torch.from_numpy(depth)[None].to(device),
                            torch.from_numpy(aligned_chain.next_start(T_cur_prev, options.scale))).cpu().numpy()
                        depth_scales.append(tracker.depth_scale)
                        if options.refine.depth_scale:
                            depth = depth * np.float32(tracker.depth_scale)
                    held = TrackedFrame(replace(frame, rgb=rgb), depth, network_pose)
                    for tracked, pose in smoother.push(aligned, held):
                        settle(tracked, pose)
                previous = images[-1:]
            for tracked, pose in smoother.flush():
                settle(tracked, pose)
            if path.count == 0:  # a source that did not know its length
                raise DataFormatError(source.description, f"no frames from --start {options.frames.start} on")
        write_json(stage / "depth" / "depth.json", {
            "unit_cm": unit, "meaning": "z-depth along the optical axis (OpenCV camera), in counts of unit_cm",
            "unknown": 0, "scale_applied": options.scale, "preview_range_cm": shown})
        path.write(stage)
        surface_started = progress.elapsed()
        mesh = write_surface(stage, volume) if volume is not None else None
        surface_seconds = progress.elapsed() - surface_started
        if mesh is not None and len(mesh.vertices) == 0:
            print(f"[reconstruct] warning: {empty_surface_warning(depth, K, volume.voxel_cm)}", file=sys.stderr)
        collapsed = collapsed_depth_warning(range_ends.share, record.params.model, "of these frames")
        if collapsed:
            print(f"[reconstruct] warning: {collapsed}", file=sys.stderr)
        ground_truth = ground_truth_in_path_world(path.gt_poses, path.poses)
        recording.finish(np.stack(path.poses), ground_truth, mesh)
        seconds = progress.elapsed()
        summary = {
            "format": RECONSTRUCTION_FORMAT, "input": source.description,
            "model": ADAPTED_MODEL if uses_fitted_model(adaptation) else str(model_path),
            **({"adaptation": adaptation.record()} if adaptation is not None else {}),
            **({"adapted_from": record.adapted_from} if record.adapted_from is not None else {}),
            "frames": path.count, "frame_range": asdict(options.frames), "native_size": list(source.native_size),
            "crop": asdict(region), "model_view": asdict(model_view(region)), "size": size,
            "K": K.tolist(), "intrinsics": intrinsics_from, "scale": options.scale, "depth_unit_cm": unit,
            "seconds": seconds, "frames_per_second": path.count / seconds,
            # the surface is extracted once, at the end: its time follows the surface seen, not the frames
            "surface_seconds": surface_seconds if mesh is not None else None, "device": str(device),
            "precision": "bf16" if compute_dtype(device, options.precision) == torch.bfloat16 else "float32",
            "threads": torch.get_num_threads(),
            "tsdf": fusion_summary(volume, options) if volume is not None else None,
            "mesh": {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
                     "blocks": volume.block_count} if mesh is not None else None,
            "field_of_view": {"share": float(valid.mean()), "frames_looked_at": FIELD_OF_VIEW_FRAMES},
            "depth_at_range_ends": range_ends.share,
            # a refined path's translations come from the keyframes' depth: it has the depth's scale
            "path": {"refined": tracker is not None, "scale_from": "depth" if tracker is not None else "pose network",
                     **({"keyframes": tracker.keyframes, "rotation_smoothing_frames": smoother.sigma_frames,
                         "depth_rescaled": depth_scale_summary(depth_scales) if options.refine.depth_scale else None}
                        if tracker is not None else {}),
                     "photometric_error": explained.means()},
            **path.ground_truth_scale(),
            **({"resume_key": resume_key} if resume_key is not None else {}),
        }
        if uses_fitted_model(adaptation):
            shutil.copyfile(used, stage / ADAPTED_MODEL)
        write_json(stage / "reconstruction.json", summary)
        write_contact_sheet(stage / "sheet.png", sampler.samples, shown, np.stack(path.poses),
                            mesh.vertices if mesh is not None else np.zeros((0, 3)),
                            mesh.colours if mesh is not None else np.zeros((0, 3), np.uint8),
                            sheet_title(source, summary), ground_truth)
    surface = f"; the surface took {surface_seconds:.1f} s of it" if mesh is not None else ""
    print(f"[reconstruct] {path.count} frames in {format_duration(seconds)} ({path.count / seconds:.1f} frames/s"
          f"{surface}) -> {out_dir}", file=sys.stderr)
    return summary


class RangeEndShare:
    """The share of the pixels in view, over every frame, whose depth (cm, before ``--scale``) sits at an end of the
    model's range (:func:`~endoflow.models.depth_range.at_depth_range_ends`): near 1, the depth has collapsed."""

    def __init__(self, cfg: ModelConfig) -> None:
        self.cfg, self.at_ends, self.in_view = cfg, 0, 0

    def add(self, depth_cm: np.ndarray, valid: np.ndarray) -> None:
        self.at_ends += int(np.count_nonzero(at_depth_range_ends(depth_cm, self.cfg) & valid))
        self.in_view += int(np.count_nonzero(valid))

    @property
    def share(self) -> float:
        return self.at_ends / max(self.in_view, 1)


class PathPhotometry:
    """How well each path explains the frames, without ground truth: the SSIM + L1 error (Monodepth2's, images in
    [0, 1]) of each frame warped into the previous one with the previous frame's depth and the path's step, over
    the pixels that land inside, averaged over frames; for the path written, the pose network's own chain and a
    constant step (the training set's mean ``T_prev_cur`` over ``stride`` frames, times ``scale``). Lower is
    better; the refined path is fitted to a like error (against keyframes), so it is favoured. The warps run on
    ``device``, the model's: at 480 px on the H100 machine's CPU they took 60 ms a frame, four times the networks'
    and the fusion's time on its GPU."""

    def __init__(self, K: np.ndarray, mean_step: np.ndarray, stride: int, scale: float,
                 device: torch.device = torch.device("cpu")) -> None:
        self.device = device
        self.K = torch.from_numpy(K).float()[None].to(device)
        constant = np.linalg.matrix_power(np.asarray(mean_step, np.float64), stride)
        constant[:3, 3] *= scale
        self.constant_step = constant  # T_prev_cur between selected frames
        self.previous: Optional[tuple[torch.Tensor, torch.Tensor]] = None
        self._pending: list[torch.Tensor] = []  # a frame's errors [3] each, on the device
        self._read: list[np.ndarray] = []  # earlier frames' errors [frames, 3], read back

    def add(self, rgb: np.ndarray, depth: np.ndarray, path: "CameraPath") -> None:
        image = torch.from_numpy(rgb).to(self.device).permute(2, 0, 1).float()[None] / 255
        if self.previous is not None:
            steps = [relative_pose(path.poses[-1], path.poses[-2]), invert_pose(self.constant_step)]
            network = relative_pose(path.network_poses[-1], path.network_poses[-2])
            if np.array_equal(network, steps[0]):  # the path written is the network's: its error, once
                errors = self._errors(*self.previous, image, np.stack(steps))[[0, 0, 1]]
            else:
                errors = self._errors(*self.previous, image, np.stack([steps[0], network, steps[1]]))
            self._pending.append(errors)
            if len(self._pending) == PHOTOMETRY_READ_FRAMES:
                self._read_back()
        self.previous = (image, torch.from_numpy(depth).to(self.device).float()[None, None])

    def _errors(self, target: torch.Tensor, depth: torch.Tensor, source: torch.Tensor, T_source_target: np.ndarray
                ) -> torch.Tensor:
        """The error of each step of ``T_source_target [n, 4, 4]``, warped together in one call."""
        count = len(T_source_target)
        return view_synthesis_error(target.expand(count, -1, -1, -1), source.expand(count, -1, -1, -1),
                                    depth.expand(count, -1, -1, -1),
                                    torch.from_numpy(T_source_target).float().to(self.device), self.K,
                                    (depth > 0).expand(count, -1, -1, -1))

    def _read_back(self) -> None:
        if self._pending:
            self._read.append(torch.stack(self._pending).cpu().numpy())
            self._pending = []

    def means(self) -> dict[str, float]:
        """Each path's error averaged over the frames (none before a second frame)."""
        self._read_back()
        if not self._read:
            return {}
        per_path = np.concatenate(self._read).T.astype(np.float64)  # a row of frames each
        return {name: float(np.mean(errors)) for name, errors in zip(PHOTOMETRY_PATHS, per_path)}


def input_intrinsics(K_native: Optional[np.ndarray], region: Crop, size: int, model: EndoflowModel,
                     assumed_fov_deg: float) -> tuple[np.ndarray, str]:
    """K at the model's ``size`` of the input's view ``region``, and where it comes from: ``K_native`` (given, in
    native pixels), else the camera the model learned intrinsics for (:func:`learned_camera`) applied to the
    assumed K, else the assumed K itself (a centred pinhole of ``assumed_fov_deg`` across the region's diagonal)."""
    if K_native is not None:
        return stored_intrinsics(crop_intrinsics(K_native, region), region.size, size), "given"
    K = stored_intrinsics(assumed_intrinsics(region.size, assumed_fov_deg), region.size, size)
    assumed = f"a centred pinhole of {assumed_fov_deg:g} degrees across the diagonal"
    camera = learned_camera(model)
    if camera is None:
        return K, f"assumed ({assumed}; no --intrinsics, and the model learned none)"
    learned = model.learned_K(camera, torch.from_numpy(K).to(model.intrinsics.corrections.device), (size, size))
    return (learned.detach().cpu().double().numpy(),
            f"learned by the model for its {camera!r} camera, from {assumed} (no --intrinsics)")


def learned_camera(model: EndoflowModel) -> Optional[str]:
    """The camera whose learned intrinsics an input of unknown intrinsics takes: the video camera where the model
    learned it (footage like the input), else the one camera it learned, else None."""
    learned = [name for index, name in enumerate(DATASETS) if model.intrinsics.learned(index)]
    if "video" in learned:
        return "video"
    return learned[0] if len(learned) == 1 else None


def input_field_of_view(source: FrameSource, frames: FrameRange, region: Crop, size: int) -> np.ndarray:
    """``size x size`` bool: where the model's view of the input sees the scene (:mod:`endoflow.data.field_of_view`),
    from its first :data:`FIELD_OF_VIEW_FRAMES` selected frames."""
    # a few frames at a time (60 frames of a 1080p video are 370 MB), decoded side by side where the input allows
    reads = (partial(cropped_rgb, read, region) for read in
             itertools.islice(source.readers(frames), FIELD_OF_VIEW_FRAMES))
    with contextlib.closing(decoded_ahead(reads, READ_AHEAD, side_threads())) as selected:
        first = next(selected, None)
        if first is None:  # no frames: the run itself says so, naming the input
            return np.ones((size, size), bool)
        try:
            return resized_field_of_view(field_of_view(itertools.chain([first], selected)), size)
        except NoFieldOfView as exc:
            raise DataFormatError(source.description, f"{exc}; --start skips dark frames at the start") from None


def cropped_rgb(read: Callable[[], InputFrame], region: Crop) -> np.ndarray:
    """The RGB of the frame ``read`` decodes, cut to ``region``."""
    return read().cropped(region).rgb


def check_frame_range(source: FrameSource, frames: FrameRange) -> None:
    """Refuse a range that starts beyond the frames of a source that knows how many it has."""
    if source.length is not None and frames.start >= source.length:
        raise DataFormatError(source.description, f"--start {frames.start} is beyond its {source.length} frames "
                                                  f"(positions 0 to {source.length - 1})")


def check_output_folder(out_dir: Path, source: FrameSource, model_path: Path, force: bool) -> None:
    """The check :func:`reconstruct` makes of ``out_dir`` before it writes (never a folder holding the input or the
    model), for a caller with minutes of work to do before it (a fit)."""
    check_replaceable(out_dir, EARLIER_RECONSTRUCTION, force, read_inputs(source, model_path), FORCE_OPTION)


def read_inputs(source: FrameSource, model_path: Path) -> tuple[str | Path, Path]:
    """What a reconstruction reads, which its output folder may never be or hold: the frames and the model as
    trained (a fit of it reconstructs from a scratch folder)."""
    return source.location, model_path


def uses_fitted_model(adaptation: Optional[Adaptation]) -> bool:
    """Whether a fit was made first and its model reconstructs."""
    return adaptation is not None and adaptation.kept


def predict_frames(model: torch.nn.Module, images: torch.Tensor, previous: Optional[torch.Tensor], scale: float,
                   model_path: Path, indices: list[int]) -> list[tuple[np.ndarray, Optional[np.ndarray]]]:
    """Per frame of ``images [B, 3, H, W]`` (frames ``indices``, in order): its depth (cm, times ``scale``) and the
    step ``T_cur_prev`` from the frame before it (``previous [1, 3, H, W]`` for the first; None at the video's
    start), each network called once for the batch.

    Raises:
        DataFormatError: naming the model file, for a NaN or infinity in either (damaged weights, a training that
            diverged): written out, it would fill the depth maps with zeros and the path with NaN.
    """
    depths = model.predict_depth(images)[:, 0].float().cpu().numpy() * scale
    earlier = images[:-1] if previous is None else torch.cat([previous, images[:-1]])
    steps = list(model.predict_pose(earlier, images[len(images) - len(earlier):]).cpu().double().numpy()
                 ) if len(earlier) else []
    steps = [None] * (len(images) - len(steps)) + steps
    for index, depth, T_cur_prev in zip(indices, depths, steps):
        for name, values in (("depth", depth), ("pose", T_cur_prev)):
            if values is not None and not np.isfinite(values).all():
                raise DataFormatError(model_path, f"the model predicts a {name} with NaN or infinity for frame "
                                                  f"{index}: its weights are damaged or its training diverged; use "
                                                  f"another model")
    return list(zip(depths, steps))


def frames_per_call(size: int, device: torch.device) -> int:
    """Frames the networks take in one call: :data:`GPU_BATCH` on a GPU; on a CPU, small frames together up to
    :data:`CPU_BATCH_PIXELS` (at 64 px, 2 cores, a batch of 8 costs 4.3 ms of depth per frame against 15.4 alone)
    and large ones alone (at 480 px a batch of 4 cost more per frame than one)."""
    if device.type == "cuda":
        return GPU_BATCH
    return max(1, min(CPU_MAX_BATCH, CPU_BATCH_PIXELS // (size * size)))


def in_batches(items: Iterator[Item], count: int) -> Iterator[list[Item]]:
    """``items`` in lists of ``count`` (the last may be shorter)."""
    while batch := list(itertools.islice(items, count)):
        yield batch


def model_inputs(source: FrameSource, frames: FrameRange, region: Crop, size: int
                 ) -> Iterator[Callable[[], tuple[InputFrame, np.ndarray]]]:
    """One call per selected frame, in order (:meth:`FrameSource.readers`: they may run side by side), that
    returns the frame cropped to ``region`` with its RGB resized to the model's ``size`` x ``size``."""
    for read in source.readers(frames):
        yield partial(model_input, read, region, size)


def model_input(read: Callable[[], InputFrame], region: Crop, size: int) -> tuple[InputFrame, np.ndarray]:
    cropped = read().cropped(region)
    return cropped, resize_rgb(cropped.rgb, size)


@dataclass(frozen=True)
class FrameOutputs:
    """What takes each frame in order: the depth unit and intrinsics the recording needs, and the side-by-side
    video, recording and contact-sheet sampler."""

    unit: float
    K: np.ndarray
    video: SideBySideVideo
    recording: Recording
    sampler: FrameSampler


def write_frame_outputs(index: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray,
                        preview: Future | Deferred,
                        outputs: FrameOutputs) -> None:
    """Frame ``index``'s entries in the video, the recording and the contact sheet's sample, once ``preview``
    (:func:`write_depth`'s, encoding beside it or here) is done: work for the write-behind thread, in frame order."""
    preview = preview.result()
    outputs.video.add(rgb, preview)
    outputs.recording.add_frame(index, rgb, depth, outputs.unit, outputs.K, pose)
    outputs.sampler.add(index, rgb, preview)


# The default voxel is one pixel's footprint at this quantile of the first frame's depth (inside the field of view):
# the far part of the scene. For a model whose depth is metric (one trained on phase-crossing data) that is close to
# the default before it followed the depth, the footprint at a quarter of the model's 20 cm range: 0.13-0.16 cm on
# the built-in S5, O1 and EndoSLAM colon at 64 px, against 0.163. Finer wastes memory and time on noise.
VOXEL_DEPTH_QUANTILE = 0.95
# What reconstruction.json says of the default voxel, and what a run over many videos keys its folders by: a folder
# fused by an earlier rule is made again.
VOXEL_DEFAULT = f"the first frame's depth ({VOXEL_DEPTH_QUANTILE:g} quantile)"


def default_voxel_cm(depth_cm: np.ndarray, K: np.ndarray) -> float:
    """About one pixel's footprint (cm) at the far part of ``depth_cm`` (its :data:`VOXEL_DEPTH_QUANTILE` over the
    known pixels; 0 is unknown), in the depth's own scale: a model whose depth is a twelfth of metric fuses with a
    twelfth of the voxel, so a voxel spans as much of the scene whatever the scale."""
    known = depth_cm[depth_cm > 0]
    if not len(known):
        raise ValueError("the voxel follows the depth, and this depth map has no known pixel")
    return float(np.quantile(known, VOXEL_DEPTH_QUANTILE) / K[0, 0])


def fusion_volume(depth_cm: np.ndarray, K: np.ndarray, options: ReconstructOptions, device: torch.device
                  ) -> TSDFVolume:
    """The TSDF volume, made at the first frame: its voxel ``options.voxel_cm``, else :func:`default_voxel_cm` of
    that frame's depth (``depth_cm``, 0 outside the field of view); its truncation ``options.trunc_cm``, else 4
    voxels."""
    voxel = options.voxel_cm or default_voxel_cm(depth_cm, K)
    return TSDFVolume(voxel, options.trunc_cm or 4 * voxel, device)


def fusion_summary(volume: TSDFVolume, options: ReconstructOptions) -> dict:
    """``reconstruction.json``'s ``tsdf``: voxel, truncation and where the voxel came from."""
    voxel_from = "given" if options.voxel_cm else VOXEL_DEFAULT
    return {"voxel_cm": volume.voxel_cm, "trunc_cm": volume.trunc_cm, "voxel_from": voxel_from}


@dataclass
class Chain:
    """A path's newest pose, ``end`` (None before its first frame), from which the next frame's step goes on: the
    pose network's own chain, and the path as the tracker aligned it, whose next frame starts one network step on
    (the path written, smoothed, ends frames behind them)."""

    end: Optional[np.ndarray] = None

    def next_start(self, T_cur_prev: Optional[np.ndarray], scale: float) -> np.ndarray:
        """The pose one network step ``T_cur_prev`` (its translation times ``scale``) on from ``end``; the identity
        for the first frame."""
        if T_cur_prev is None:
            return np.eye(4)
        step = np.array(T_cur_prev)
        step[:3, 3] *= scale
        return chain_step(self.end, step)

    def step(self, T_cur_prev: Optional[np.ndarray], scale: float) -> np.ndarray:
        """Move ``end`` on by the step (:meth:`next_start`) and return it."""
        self.end = self.next_start(T_cur_prev, scale)
        return self.end


@dataclass(frozen=True)
class TrackedFrame:
    """A frame waiting for its pose on the path written: what follows from it once it has one. Its colour is the
    model's input (``size`` x ``size``): the native frame, which nothing after the model reads, is not held."""

    frame: InputFrame
    depth: np.ndarray
    network_pose: np.ndarray


@dataclass
class CameraPath:
    """The camera-to-world poses (refined or the network's), the network's own chain, their timestamps and frame
    indices; with ground truth where known."""

    poses: list[np.ndarray] = field(default_factory=list)
    network_poses: list[np.ndarray] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    indices: list[int] = field(default_factory=list)
    gt_poses: list[Optional[np.ndarray]] = field(default_factory=list)
    depth_ratios: list[float] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.poses)

    def add(self, frame: InputFrame, pose: np.ndarray, network_pose: np.ndarray, depth: np.ndarray,
            size: int) -> None:
        """Append the frame's pose and the network's."""
        self.poses.append(pose)
        self.network_poses.append(network_pose)
        self.timestamps.append(frame.timestamp)
        self.indices.append(frame.index)
        self.gt_poses.append(frame.T_world_cam)
        if frame.depth_cm is not None:
            gt = resize_depth(np.asarray(frame.depth_cm, np.float32), size)  # the crop and resize the frame had
            valid = (gt > 0) & (depth > 0)
            if valid.any():
                self.depth_ratios.append(float(np.median(gt[valid]) / np.median(depth[valid])))

    def write(self, stage: Path) -> None:
        from endoflow.data.trajectory_files import write_kitti, write_simcol_relative_poses, write_tum

        poses = np.stack(self.poses)
        write_tum(stage / "trajectory.tum", np.array(self.timestamps), poses)
        write_kitti(stage / "trajectory.kitti", poses)
        if len(poses) > 1:
            write_simcol_relative_poses(stage / "simcol", self.indices, poses)
        if not np.array_equal(poses, np.stack(self.network_poses)):
            write_tum(stage / NETWORK_PATH_FILE, np.array(self.timestamps), np.stack(self.network_poses))

    def ground_truth_scale(self) -> dict:
        """The factor that brings the model's depth to the ground truth's (median over frames of the per-frame
        median ratio, as the paper's protocol scales), where the input has ground-truth depth."""
        if not self.depth_ratios:
            return {}
        return {"ground_truth_scale": {"median": float(np.median(self.depth_ratios)),
                                       "spread": float(np.std(self.depth_ratios)), "frames": len(self.depth_ratios)}}


def depth_scale_summary(scales: list[float]) -> dict:
    """What ``reconstruction.json`` says of the depth rescaled to its keyframes (``refine.depth_scale``): the
    factors on the frames' depth (the first frame's is 1): their range and the last."""
    return {"min": float(min(scales)), "max": float(max(scales)), "last": float(scales[-1])}


def preview_range(depth: np.ndarray, model_cfg: ModelConfig, scale: float) -> tuple[float, float]:
    """The depth range the previews colour: the first frame's 2nd to 98th percentile widened 1.5 times each way,
    within the model's range. The model's whole range (0.1 to 20 cm by default) would leave a colon seen at 1 to
    5 cm in one dark colour; one range for the run keeps colours comparable between frames."""
    low, high = np.percentile(depth[depth > 0] if (depth > 0).any() else depth, [2, 98])
    return (float(max(low / 1.5, model_cfg.min_depth * scale)),
            float(min(high * 1.5, model_cfg.max_depth * scale)))


def write_depth(stage: Path, index: int, depth: np.ndarray, unit: float, npy: bool,
                shown: tuple[float, float]) -> np.ndarray:
    """The frame's 16-bit depth PNG (and ``.npy``) and its preview (inverse depth over ``shown``, cm), which is
    returned."""
    counts, _ = depth_to_counts(depth, unit)
    write_bytes(stage / "depth" / f"{index:06d}.png", encode_png(counts), durable=False)
    if npy:
        with (stage / "depth" / f"{index:06d}.npy").open("wb") as out:
            np.save(out, depth.astype(np.float32))
    preview = depth_preview(depth, *shown)
    write_bytes(stage / "preview" / f"{index:06d}.png", encode_png(preview), durable=False)
    return preview


def write_surface(stage: Path, volume: TSDFVolume) -> SurfaceMesh:
    """``mesh.ply`` and ``points.ply`` (the mesh's coloured vertices); returns the mesh."""
    mesh = volume.extract_mesh()
    write_ply(stage / "mesh.ply", mesh.vertices, mesh.colours, mesh.triangles)
    write_ply(stage / "points.ply", mesh.vertices, mesh.colours)
    return mesh


def empty_surface_warning(depth_cm: np.ndarray, K: np.ndarray, voxel_cm: float) -> str:
    """Why a fused surface can be empty and what helps, from the last frame's ``depth_cm`` (cm, 0 unknown)."""
    known = depth_cm[depth_cm > 0]
    if not len(known):
        return "the fused surface is empty, and the last frame has no depth inside the field of view"
    median = float(np.median(known))
    return (f"the fused surface is empty: no cube of voxels was seen on all its corners across the surface (voxel "
            f"{voxel_cm:.3g} cm, the last frame's median depth {median:.3g} cm); --voxel-cm about the pixel "
            f"footprint there, {median / float(K[0, 0]):.2g} cm, gives the frames' surface")


def sheet_title(source: FrameSource, summary: dict) -> str:
    fitted = summary.get("ground_truth_scale")
    scale = f", ground truth = model depth x {fitted['median']:.3g}" if fitted else ""
    return (f"{source.description}: {summary['frames']} frames at {summary['size']} px, "
            f"{summary['frames_per_second']:.1f} frames/s{scale}")


def report_progress(done: int, progress: Progress) -> None:
    """A line every 25 frames and at the last one."""
    if done % 25 and not progress.finished(done):
        return
    print(f"[reconstruct] {progress.update(done)}", file=sys.stderr)


def source_frame_count(source: FrameSource, frames: FrameRange) -> Optional[int]:
    """Frames the range selects, where the source knows its length (a video may not)."""
    length = source.length
    if length is None:
        return None
    stop = min(length, frames.stop) if frames.stop is not None else length
    return max(0, math.ceil((stop - frames.start) / frames.stride))


def log_reconstruction(params: Params, project_root: Path, model_run_id: Optional[str], name: str,
                       out_dir: Path) -> RunHandle:
    """Log a reconstruction's :data:`LOGGED_OUTPUTS` as artifacts under ``reconstruct/<name>/`` of the model's
    MLflow run (or of the run :func:`endoflow.tracking.run_for_model` opens for a model whose run the store
    lacks, with a warning); returns the run."""
    from endoflow import tracking  # MLflow takes seconds to import: only runs that log pay for it
    run = tracking.run_for_model(params, project_root, model_run_id, "reconstruct")
    for file in LOGGED_OUTPUTS:
        if (out_dir / file).is_file():
            run.log_artifact(out_dir / file, f"reconstruct/{name}")
    return run
