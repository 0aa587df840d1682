"""Evaluate a trained model on one test set, with trivial baselines on the same frames in the same run.

Every frame of each test sequence, in order (:mod:`endoflow.data.sequences`), goes through the networks on
``eval.device`` under ``eval.precision``; with ``refine.enabled`` the pose network's path is also refined against
keyframes (:mod:`endoflow.geometry.direct_alignment`), its orientations smoothed over ``refine.rotation_smoothing``
frames (:mod:`endoflow.geometry.path_smoothing`), and scored as the method ``refined``. Depth is scored in the
paper's and SimCol3D's protocols beside ``constant_depth`` and ``mean_depth_map``, pose in SimCol3D's, EndoSLAM's
and the motion protocol beside ``constant_velocity``, and the model's scale consistency
(:mod:`endoflow.evaluation.metrics`, :mod:`endoflow.evaluation.baselines`); every figure goes into one long table
(:mod:`endoflow.evaluation.scores`). What is written, with units: docs/outputs.md, "evaluate@<test set>".

Fed like training (:func:`evaluate_test_set`): ``train.loader_workers`` loader processes read the shards, decode
each frame's one image and depth and score the depth baselines, which need no model (:class:`EvaluationFeed`);
this thread runs the networks on batches of ``eval.batch_size`` frames; on a GPU a second thread records each
batch (refined path, the model's scores, challenge files) while the next is predicted, its per-frame scoring
spread over ``threads`` threads. Batches come, are predicted and are recorded in sequence order, so every output
is the same whatever the number of processes and threads.
"""

from __future__ import annotations

import time
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Callable, Collection, Iterable, Iterator, Optional, TypeVar

import cv2
import numpy as np
import pandas as pd
import torch
from torch.utils.data import IterableDataset

from endoflow import tracking
from endoflow.config import Params, EvalSetConfig, Precision
from endoflow.evaluation import metrics, plots
from endoflow.evaluation.baselines import baseline_depths, baseline_relative_poses
from endoflow.evaluation.scores import (
    DEPTH_METHODS,
    POSE_METHODS,
    per_frame_table,
    per_sequence_table,
    protocol_summary,
    score_rows,
    scores_table,
)
from endoflow.evaluation.results import EVALUATION_FILE, dvc_metrics, figure_rows, mlflow_metrics
from endoflow.io import FIGURE_FOLDER, marked_output, save_figure, staged_directory, write_csv, write_json
from endoflow.data.base import slug
from endoflow.data.trajectory_files import write_simcol_relative_pose
from endoflow.data.loader import failures_passed_on, loader_turn, ordered_loader
from endoflow.data.sequences import FrameRecord, frame_sources, read_frame
from endoflow.data.shard_format import ShardEntry, has_ground_truth, manifest_location, read_manifest, shard_entries
from endoflow.devices import (autocast, images_to_device, resolve_device, to_compute_layout, unit_float_images,
                              use_cpu_threads)
from endoflow.geometry.direct_alignment import KeyframeTracker, TrackerSettings, tracker_settings
from endoflow.geometry.path_smoothing import smooth_path_orientations
from endoflow.locations import absolute_location
from endoflow.models.endoflow_model import load_trained_model
from endoflow.models.mlflow_model import is_model_uri, local_model_file
from endoflow.models.model_file import TrainingBaselines

Frame = TypeVar("Frame")  # anything with the ``sequence`` it belongs to: a frame, or where one is


@dataclass
class SequenceResult:
    """What one sequence's protocols are computed from, gathered while its frames stream past."""

    name: str
    group: str
    frames: list[int] = field(default_factory=list)
    poses: list[Optional[np.ndarray]] = field(default_factory=list)
    predicted_relative: list[np.ndarray] = field(default_factory=list)  # Q'_i between frames i and i+1
    gaps: set[int] = field(default_factory=set)  # indices of frames that follow missing frames
    depth_frames: list[int] = field(default_factory=list)
    # frames with GT only, encoded as the challenge's files are (float16 depth / 20 cm), so the challenge
    # protocol sees the same quantisation as the official scorer
    depth_pred: list[np.ndarray] = field(default_factory=list)
    depth_gt: list[np.ndarray] = field(default_factory=list)
    # per frame (as ``frames``), the paper protocol's median scaling of the model's depth; None without GT depth
    depth_ratios: list[Optional[float]] = field(default_factory=list)
    # per frame, T_world_cam of the refined path as the tracker aligned it (endoflow.geometry.direct_alignment),
    # from an identity first pose; scored with its orientations smoothed (refined_path)
    refined: list[np.ndarray] = field(default_factory=list)
    # per frame, the tracker's factor on its depth (refine.depth_scale; 1 without it): the refined path's scale is
    # the depth's so rescaled
    depth_scales: list[float] = field(default_factory=list)


# ------------------------------------------------------------------------------------------ selection
def eval_set(params: Params, name: str) -> EvalSetConfig:
    """``params.eval.test_sets[name]``, or a clear error listing the known test sets."""
    if name not in params.eval.test_sets:
        raise ValueError(f"unknown test set {name!r}; params.eval.test_sets has {sorted(params.eval.test_sets)}")
    return params.eval.test_sets[name]


def eval_set_folder(shards_root: str, test_set: EvalSetConfig) -> str:
    """The shard folder of ``test_set``'s dataset."""
    return f"{shards_root.rstrip('/')}/{test_set.dataset}"


def eval_set_shards(shards_root: str, test_set: EvalSetConfig) -> list[str]:
    """Shard URLs (in order) that hold samples of ``test_set``, from the dataset's ``manifest.parquet``."""
    base = eval_set_folder(shards_root, test_set)
    manifest = read_manifest(base)
    table = manifest.table.to_pandas()
    rows = table[table["split"] == test_set.split]
    if test_set.groups:
        rows = rows[rows["group"].isin(test_set.groups)]
    if test_set.sequences:
        rows = rows[rows["sequence"].isin(test_set.sequences)]
    if rows.empty:
        raise ValueError(
            f"{manifest.location}: no {test_set.split} samples of groups {test_set.groups or 'any'} and "
            f"sequences {test_set.sequences or 'any'} (found groups {sorted(table['group'].unique())})")
    return [f"{base}/{name}" for name in sorted(rows["shard"].unique())]


def belongs_to(meta: dict, test_set: EvalSetConfig) -> bool:
    """Whether a sample is of the test set; one of a dataset without ground truth is refused (see
    :func:`refuse_unlabelled`)."""
    keep = (meta["split"] == test_set.split
            and (not test_set.groups or meta["group"] in test_set.groups)
            and (not test_set.sequences or meta["sequence"] in test_set.sequences))
    if keep:
        refuse_unlabelled(meta, test_set)
    return keep


def refuse_unlabelled(meta: dict, test_set: EvalSetConfig) -> None:
    """Evaluation scores depth and poses against ground truth: a sample of a dataset that has neither (unlabelled
    video) has nothing to be scored against."""
    if not (has_ground_truth(meta, "depth") or has_ground_truth(meta, "pose")):
        raise ValueError(
            f"test set of dataset {test_set.dataset!r}: sequence {meta['sequence']} has no ground-truth depth or "
            f"poses ({meta['dataset']} is unlabelled), and evaluation scores against them; measure unlabelled video "
            f"by the photometric error of held-out frames (training's val_photometric, endoflow adapt)")


# ------------------------------------------------------------------------------------------- frames
def batches_within_sequences(frames: Iterable[Frame], size: int) -> Iterator[list[Frame]]:
    """Consecutive frames in lists of at most ``size``, never mixing two sequences."""
    batch: list[Frame] = []
    for frame in frames:
        if batch and (len(batch) == size or frame.sequence != batch[0].sequence):
            yield batch
            batch = []
        batch.append(frame)
    if batch:
        yield batch


@dataclass(frozen=True)
class FrameBatch:
    """Consecutive frames of one sequence with what is scored of them without the model: per frame with GT depth,
    the depth baselines' paper-protocol errors (method -> figures, in :func:`baseline_depths`' order), else None."""

    frames: list[FrameRecord]
    baseline_errors: list[Optional[dict[str, dict[str, float]]]]

    def __reduce__(self) -> tuple:
        # From a loader process as two tensors (the images, the GT depth maps), which torch hands over through
        # shared memory; a tensor per frame and the maps copied through a pipe took four times as long (35 against
        # 9 ms a batch of 16 frames of 480 px on 2 cores)
        return _unpacked_frame_batch, _packed_frame_batch(self)


def _packed_frame_batch(batch: FrameBatch) -> tuple:
    with_depth = [index for index, frame in enumerate(batch.frames) if frame.depth_cm is not None]
    images = torch.stack([frame.rgb for frame in batch.frames])
    depth = torch.from_numpy(np.stack([batch.frames[index].depth_cm for index in with_depth])) if with_depth else None
    bare = [replace(frame, rgb=None, depth_cm=None) for frame in batch.frames]
    return bare, images, depth, with_depth, batch.baseline_errors


def _unpacked_frame_batch(bare: list[FrameRecord], images: torch.Tensor, depth: Optional[torch.Tensor],
                          with_depth: list[int], baseline_errors: list) -> FrameBatch:
    depths = dict(zip(with_depth, depth.numpy())) if depth is not None else {}
    return FrameBatch([replace(frame, rgb=image, depth_cm=depths.get(index))
                       for index, (frame, image) in enumerate(zip(bare, images))], baseline_errors)


def frame_batch(frames: list[FrameRecord], baselines: TrainingBaselines) -> FrameBatch:
    """``frames`` with their baselines' depth errors."""
    return FrameBatch(frames, [None if frame.depth_cm is None else baseline_depth_errors(frame.depth_cm, baselines)
                               for frame in frames])


def baseline_depth_errors(gt_cm: np.ndarray, baselines: TrainingBaselines) -> dict[str, dict[str, float]]:
    """The paper-protocol errors of each depth baseline against one GT depth map."""
    return {method: metrics.paper_depth_errors(gt_cm, depth)
            for method, depth in baseline_depths(baselines, gt_cm.shape).items()}


@dataclass(frozen=True)
class EvaluationFeed(IterableDataset):
    """A test set's frames in batches (:class:`FrameBatch`) of at most ``batch_size`` consecutive frames of one
    sequence (:func:`batches_within_sequences`), in sequence order, for :func:`~endoflow.data.loader.ordered_loader`.

    Loader process ``w`` of ``W`` hands over batches ``w, w + W, ...``: it reads every shard whole (each is checked
    to its end), plans the frame order from the samples' ``meta.json`` and decodes and scores only its own batches.
    Frames come with 8-bit RGB. ``keep`` as :func:`~endoflow.data.sequences.sequence_frames` takes it; ``entries``:
    the shards' manifest entries.
    """

    urls: list[str]
    entries: dict[str, ShardEntry]
    keep: Callable[[dict], bool]
    max_frames: Optional[int]
    batch_size: int
    baselines: TrainingBaselines

    def __iter__(self) -> Iterator[FrameBatch]:
        worker, workers = loader_turn()
        sources = frame_sources(self.urls, self.keep, self.max_frames, self.entries)
        own = (frame_batch([read_frame(source) for source in batch], self.baselines)
               for index, batch in enumerate(batches_within_sequences(sources, self.batch_size))
               if index % workers == worker)
        yield from failures_passed_on(own)


@dataclass(frozen=True)
class BatchPrediction:
    """The networks' answers for one batch: ``depth [B, H, W]`` (float32, cm) of its frames; ``relative
    [len(pairs), 4, 4]`` (float64), ``T_earlier_later`` of each ``(earlier, later)`` pair of consecutive frames (the
    first pair's earlier frame ends the previous batch where the sequence goes on); per frame, where the refined
    path starts anew (a sequence's first frame, a frame after missing ones), the K it is tracked with, else None."""

    depth: np.ndarray
    pairs: list[tuple[FrameRecord, FrameRecord]]
    relative: np.ndarray
    tracker_K: list[Optional[torch.Tensor]]


# ------------------------------------------------------------------------------------- prediction
class SequenceEvaluator:
    """Runs the model over ordered frames, writes challenge predictions and gathers per-sequence results; the
    per-image depth errors go straight into ``scores``, rows of :mod:`endoflow.evaluation.scores`' table.

    A batch is predicted (:meth:`predict`: the networks, on ``device``), then recorded (:meth:`record`: the refined
    path, scores, files; ``scoring`` threads score its frames, else this one); :meth:`process` does both. Batches are
    predicted in order and recorded in that order, recording in another thread than predicting if need be.
    """

    def __init__(self, model: torch.nn.Module, baselines: TrainingBaselines, predictions_dir: Path,
                 device: torch.device, precision: Precision, max_examples: int,
                 refine: Optional[TrackerSettings] = None, scoring: Optional[Executor] = None) -> None:
        self.model = model
        self.refine = refine
        self.tracker: Optional[KeyframeTracker] = None
        self.max_examples = max_examples
        self.baselines = baselines
        self.predictions_dir = predictions_dir
        self.device = device
        self.precision = precision
        self.scoring = scoring
        self.sequences: list[SequenceResult] = []
        self.scores: list[dict] = []
        self.examples: list[dict] = []
        self._carry: Optional[FrameRecord] = None
        self.frames_done = 0

    def process(self, batch: list[FrameRecord]) -> None:
        """One batch of consecutive frames of one sequence, predicted and recorded."""
        self.record(frame_batch(batch, self.baselines), self.predict(batch))

    @torch.inference_mode()
    def predict(self, frames: list[FrameRecord]) -> BatchPrediction:
        """The networks on one batch, the frames copied to the device once: the depth of each frame and the poses
        between consecutive frames, the first from the previous batch's last frame where the sequence goes on."""
        if self._carry is not None and self._carry.sequence != frames[0].sequence:
            self._carry = None
        carried = [self._carry] if self._carry is not None else []
        chain = carried + frames
        images = self._images(chain)
        with autocast(self.device, self.precision):
            depth = self.model.predict_depth(images[len(carried):])
        depth = depth[:, 0].float().cpu().numpy()
        relative = np.zeros((0, 4, 4))
        if len(chain) > 1:
            # T_earlier_later = inv(P_earlier) @ P_later: the challenge's relative pose
            with autocast(self.device, self.precision):
                relative = self.model.predict_pose(images[1:], images[:-1], source_is_next=False)
            relative = relative.double().cpu().numpy()
        starts = [frame.after_gap or (index == 0 and not carried) for index, frame in enumerate(frames)]
        tracker_K = [self._camera_K(frame) if start and self.refine is not None else None
                     for frame, start in zip(frames, starts)]
        self._carry = frames[-1]
        return BatchPrediction(depth, list(zip(chain[:-1], chain[1:])), relative, tracker_K)

    @torch.inference_mode()
    def record(self, batch: FrameBatch, prediction: BatchPrediction) -> None:
        """What one predicted batch leaves: challenge files, the refined path, per-frame scores."""
        frames = batch.frames
        result = self._sequence_for(frames[0])
        for (earlier, later), pose in zip(prediction.pairs, prediction.relative):
            if not later.after_gap:  # no challenge pose across missing frames; never scored either
                self._write_pose(earlier, later, pose)
            result.predicted_relative.append(pose)
        if self.refine is not None:
            self._track(result, frames, prediction)
        spread = self.scoring.map if self.scoring is not None else map
        scored = list(spread(self._score_frame, frames, prediction.depth))
        for frame, depth, model, baselines in zip(frames, prediction.depth, scored, batch.baseline_errors):
            self._add_frame(result, frame, depth, model, baselines)
        self.frames_done += len(frames)

    def _track(self, result: SequenceResult, frames: list[FrameRecord], prediction: BatchPrediction) -> None:
        """Each frame's refined pose, aligned to the tracker's keyframe from the pose network's step; the tracker
        starts anew with each sequence and after missing frames."""
        # the frames as read, not the device's copy (bf16 under autocast on a GPU)
        images = unit_float_images(torch.stack([frame.rgb for frame in frames]))
        # the step into each frame of the batch; the sequence's first frame has none
        steps = [None] * (len(frames) - len(prediction.relative)) + list(prediction.relative)
        for image, depth, step, K in zip(images, prediction.depth, steps, prediction.tracker_K):
            if K is not None:  # a sequence's K is its own
                self.tracker = KeyframeTracker(K, self.refine)
            start = np.eye(4) if step is None else result.refined[-1] @ step
            result.refined.append(self.tracker.track(image, torch.from_numpy(depth)[None],
                                                     torch.from_numpy(start)).numpy())
            result.depth_scales.append(self.tracker.depth_scale)

    def _camera_K(self, frame: FrameRecord) -> torch.Tensor:
        """The frame's K, or where it is assumed (a camera nobody calibrated) its camera's learned one."""
        K = torch.from_numpy(frame.K)
        if frame.intrinsics_known:
            return K
        learned = self.model.learned_K(frame.dataset, K.to(self.device), tuple(frame.rgb.shape[-2:]))
        return learned.detach().cpu().double()

    def _images(self, frames: list[FrameRecord]) -> torch.Tensor:
        return images_to_device(torch.stack([f.rgb for f in frames]), self.device, self.precision)

    def _sequence_for(self, frame: FrameRecord) -> SequenceResult:
        if not self.sequences or self.sequences[-1].name != frame.sequence:
            if any(s.name == frame.sequence for s in self.sequences):
                raise ValueError(f"sequence {frame.sequence} appears twice in the test shards")
            self.sequences.append(SequenceResult(frame.sequence, frame.group))
        return self.sequences[-1]

    def _score_frame(self, frame: FrameRecord, prediction: np.ndarray) -> Optional[tuple[dict, np.ndarray]]:
        """Writes the frame's challenge depth file; with GT depth, the model's paper-protocol errors and its depth as
        that file holds it. Frames may be scored in any order and at once."""
        self._write_depth(frame, prediction)
        if frame.depth_cm is None:
            return None
        return (metrics.paper_depth_errors(frame.depth_cm, prediction),
                metrics.depth_to_simcol_unit(prediction).astype(np.float16))

    def _add_frame(self, result: SequenceResult, frame: FrameRecord, prediction: np.ndarray,
                   model: Optional[tuple[dict, np.ndarray]], baselines: Optional[dict[str, dict]]) -> None:
        """One frame into its sequence's results, in order: ``model`` from :meth:`_score_frame`, ``baselines`` from
        :func:`baseline_depth_errors`."""
        if frame.after_gap:
            result.gaps.add(len(result.frames))
        result.frames.append(frame.frame)
        result.poses.append(frame.pose)
        result.depth_ratios.append(None)
        if model is None or baselines is None:
            return
        errors, challenge_depth = model
        result.depth_frames.append(frame.frame)
        result.depth_pred.append(challenge_depth)
        result.depth_gt.append(frame.depth_cm)
        for method, figures in (("model", errors), *baselines.items()):
            self.scores += score_rows(frame.sequence, frame.frame, method, "depth_paper", figures)
        result.depth_ratios[-1] = errors["ratio"]
        if len(result.depth_frames) == 1 and len(self.examples) < self.max_examples:
            self.examples.append({"label": f"{frame.sequence} #{frame.frame}", "gt": frame.depth_cm,
                                  "rgb": unit_float_images(frame.rgb).permute(1, 2, 0).numpy(), "pred": prediction})

    def _frame_folder(self, frame: FrameRecord) -> Path:
        return self.predictions_dir / f"{slug(frame.group or 'test')}_Test" / f"Frames_{slug(frame.sequence)}_OP"

    def _write_depth(self, frame: FrameRecord, depth_cm: np.ndarray) -> None:
        side = min(frame.native_size)  # the stored image is the centred square crop of the native frame
        native = cv2.resize(depth_cm, (side, side), interpolation=cv2.INTER_LINEAR)
        path = self._frame_folder(frame) / "depth" / f"FrameBuffer_{frame.frame:04d}.npy"
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, metrics.depth_to_simcol_unit(native).astype(np.float16))

    def _write_pose(self, earlier: FrameRecord, later: FrameRecord, relative: np.ndarray) -> None:
        # inside the staged predictions folder: its swap makes the files visible, no fsync per file
        write_simcol_relative_pose(self._frame_folder(earlier), earlier.frame, later.frame, relative,
                                   durable=False)


# -------------------------------------------------------------------------------------- scoring
def score_sequences(evaluator: SequenceEvaluator) -> tuple[dict, pd.DataFrame, pd.DataFrame, dict]:
    """Aggregate metrics, per-frame table, per-sequence table and trajectories from a finished evaluator."""
    rows = list(evaluator.scores)
    trajectories: dict = {}
    smoothing = evaluator.refine.rotation_smoothing if evaluator.refine is not None else 0.0
    for seq in evaluator.sequences:
        rows += depth_sequence_scores(seq, evaluator.baselines)
        pose_rows, trajectory = pose_sequence_scores(seq, evaluator.baselines, smoothing)
        rows += pose_rows
        if trajectory is not None:
            trajectories[seq.name] = trajectory
    scores = scores_table(rows)
    frames = pd.DataFrame([{"sequence": seq.name, "frame": f} for seq in evaluator.sequences for f in seq.frames],
                          columns=["sequence", "frame"])
    sequences = pd.DataFrame([{"sequence": seq.name, "group": seq.group, "frames": len(seq.frames)}
                              for seq in evaluator.sequences])
    return protocol_summary(scores), per_frame_table(frames, scores), per_sequence_table(sequences, scores), \
        trajectories


def depth_sequence_scores(seq: SequenceResult, training: TrainingBaselines) -> list[dict]:
    """The challenge's depth protocol over one sequence's frames with GT depth, for the model and the baselines:
    the sequence's figures and each frame's L1."""
    if not seq.depth_frames:
        return []
    gt = np.stack(seq.depth_gt)
    predicted = {"model": np.stack(seq.depth_pred).astype(np.float32) * metrics.SIMCOL_DEPTH_RANGE_CM,
                 **{method: np.broadcast_to(depth, gt.shape)
                    for method, depth in baseline_depths(training, gt.shape[1:]).items()}}
    rows: list[dict] = []
    for method, pred in predicted.items():
        result = metrics.simcol_depth_sequence(pred, gt)
        rows += score_rows(seq.name, None, method, "depth_simcol",
                           {key: result[key] for key in metrics.SIMCOL_DEPTH_KEYS})
        for frame, l1 in zip(seq.depth_frames, result["per_frame"]["l1"]):
            rows += score_rows(seq.name, frame, method, "depth_simcol", {"l1": l1})
    return rows


def pose_sequence_scores(seq: SequenceResult, training: TrainingBaselines, rotation_smoothing: float = 0.0
                         ) -> tuple[list[dict], Optional[dict]]:
    """The challenge's, EndoSLAM's and the motion protocols over the longest run of one sequence's posed frames, for
    the model (its network's and its refined path, :func:`refined_path`) and constant velocity, and the scale
    consistency of the model's paths where the run has GT depth: the sequence's figures, each frame's RTE and ROT,
    and the trajectories."""
    run = longest_posed_run(seq.poses, seq.gaps)
    if run is None:
        return [], None
    start, stop = run
    gt_poses = np.stack(seq.poses[start:stop])
    predicted = {"model": np.stack(seq.predicted_relative[start:stop - 1]),
                 **({"refined": metrics.relative_poses(refined_path(seq, rotation_smoothing)[start:stop])}
                    if seq.refined else {}),
                 **baseline_relative_poses(training, stop - start - 1)}
    trajectory = {"gt": gt_poses[:, :3, 3], "frames": seq.frames[start:stop]}
    rows: list[dict] = []
    for method, relative in predicted.items():
        result = metrics.simcol_pose_sequence(gt_poses, relative)
        rows += score_rows(seq.name, None, method, "pose_simcol", {k: result[k] for k in metrics.SIMCOL_POSE_KEYS})
        endoslam = metrics.endoslam_pose_sequence(gt_poses, relative)
        rows += score_rows(seq.name, None, method, "pose_endoslam",
                           {k: endoslam[k] for k in metrics.ENDOSLAM_POSE_KEYS})
        if len(relative) >= 2:
            rows += score_rows(seq.name, None, method, "pose_motion", metrics.motion_agreement(gt_poses, relative))
        for i, frame in enumerate(seq.frames[start + 1:stop]):
            rows += score_rows(seq.name, frame, method, "pose_simcol",
                               {"rte": result["per_frame"]["rte"][i], "rot": result["per_frame"]["rot"][i]})
        trajectory[method] = result["trajectory"][:, :3, 3]
    for method in ("model", "refined"):
        ratios = scaled_depth_ratios(seq, start, stop, rescaled=method == "refined")
        if ratios and method in predicted and np.any(predicted[method][:, :3, 3]):
            rows += score_rows(seq.name, None, method, "scale",
                               metrics.scale_consistency(gt_poses, predicted[method], ratios))
    return rows, trajectory


def scaled_depth_ratios(seq: SequenceResult, start: int, stop: int, rescaled: bool) -> list[float]:
    """The per-frame median ratios of GT over predicted depth of frames ``start:stop`` that have GT depth; with
    ``rescaled``, of the depth as the tracker rescaled it (``refine.depth_scale``), whose scale the refined path
    has."""
    scales = seq.depth_scales if rescaled and seq.depth_scales else [1.0] * len(seq.depth_ratios)
    return [ratio / scale for ratio, scale in zip(seq.depth_ratios[start:stop], scales[start:stop])
            if ratio is not None]


def refined_path(seq: SequenceResult, rotation_smoothing: float) -> np.ndarray:
    """``[N, 4, 4]``: the sequence's refined path as `reconstruct` writes one, each stretch the tracker followed
    without a break (it starts anew after missing frames) with its orientations smoothed over ``rotation_smoothing``
    frames (:mod:`endoflow.geometry.path_smoothing`)."""
    bounds = sorted({0, len(seq.refined), *(gap for gap in seq.gaps if 0 < gap < len(seq.refined))})
    return np.concatenate([smooth_path_orientations(np.stack(seq.refined[a:b]), rotation_smoothing)
                           for a, b in zip(bounds[:-1], bounds[1:])])


def longest_posed_run(poses: list[Optional[np.ndarray]], gaps: Collection[int] = ()) -> Optional[tuple[int, int]]:
    """``(start, stop)`` of the longest run of consecutive frames with GT poses (at least two), else None.

    A run ends before a frame in ``gaps`` (one that follows missing frames), which may start the next one.
    """
    best: Optional[tuple[int, int]] = None
    start = None
    for i, pose in enumerate([*poses, None]):
        if start is not None and (pose is None or i in gaps):
            if i - start >= 2 and (best is None or i - start > best[1] - best[0]):
                best = (start, i)
            start = None
        if pose is not None and start is None:
            start = i
    return best


# --------------------------------------------------------------------------------------- driver
def evaluate_test_set(params: Params, name: str, urls: list[str], model_path: str | Path,
                      out_metrics: Path, out_plots: Path, out_predictions: Path) -> dict:
    """Evaluate the model in ``model_path`` on test set ``name``, read from its shards ``urls`` (in order, as
    :func:`eval_set_shards` lists them); write all outputs.

    The frames are read by ``train.loader_workers`` loader processes (0: this process) and, on a GPU, recorded
    beside the networks by ``threads`` threads (the module docstring); neither count changes any output.

    Returns the full result (with ``mlflow_run_id`` of the training run), written to
    ``<out_predictions>/evaluation.json``; ``out_metrics`` gets its headline (:mod:`endoflow.evaluation.results`).
    """
    test_set = eval_set(params, name)
    device = resolve_device(params.eval.device, "eval.device")
    model, record = load_trained_model(model_path, device)
    model = to_compute_layout(model, device, params.eval.precision, params.data.size)
    started = time.perf_counter()
    earlier = marked_output(f"the predictions of test set {name}", EVALUATION_FILE, test_set=name)
    # On a CPU the networks' threads (``threads``) already take the cores: a recording thread beside them would gain
    # no core of its own, only make their OpenMP threads wait for one another whenever one is descheduled
    overlapped = device.type != "cpu"
    with staged_directory(out_predictions, earlier) as predictions_dir, ThreadPoolExecutor(params.threads) as scoring:
        refine = tracker_settings(params.refine) if params.refine.enabled else None
        evaluator = SequenceEvaluator(model, record.baselines, predictions_dir, device, params.eval.precision,
                                      params.eval.depth_examples, refine, scoring if overlapped else None)
        record_test_set(evaluator, params, test_set, urls, params.train.loader_workers, overlapped)
        if not evaluator.sequences:
            raise ValueError(f"test set {name}: no frames found in the selected shards")
        elapsed = time.perf_counter() - started
        summary, frames_table, sequences_table, trajectories = score_sequences(evaluator)
        result = {
            "test_set": name,
            "dataset": test_set.dataset,
            "sequences": len(evaluator.sequences),
            "frames": evaluator.frames_done,
            "depth_frames": int(sum(len(s.depth_frames) for s in evaluator.sequences)),
            **summary,
            "frames_per_second": evaluator.frames_done / max(elapsed, 1e-9),
            "mlflow_run_id": record.mlflow_run_id,
        }
        write_tables(predictions_dir, frames_table, sequences_table, trajectories)
        write_json(predictions_dir / EVALUATION_FILE, result)
    write_plots(name, out_plots, evaluator, frames_table, trajectories)
    write_json(out_metrics, dvc_metrics(name, result))
    return result


def record_test_set(evaluator: SequenceEvaluator, params: Params, test_set: EvalSetConfig, urls: list[str],
                    loader_workers: int, overlapped: bool) -> None:
    """Every frame of ``test_set`` in its shards ``urls``, read by ``loader_workers`` loader processes (0: this
    process), through ``evaluator`` (:func:`predict_then_record`)."""
    feed = EvaluationFeed(urls, shard_entries(urls), partial(belongs_to, test_set=test_set),
                          params.eval.max_frames_per_sequence, params.eval.batch_size, evaluator.baselines)
    predict_then_record(evaluator, ordered_loader(feed, loader_workers), overlapped)


def predict_then_record(evaluator: SequenceEvaluator, batches: Iterable[FrameBatch], overlapped: bool) -> None:
    """Each batch through the networks in this thread, then recorded: ``overlapped``, in a second thread while the
    next is predicted, so that the device does not wait for the scoring (one batch recorded at a time, in order; an
    error in either thread is raised here once the batch being recorded is done), else here."""
    if not overlapped:
        for batch in batches:
            evaluator.record(batch, evaluator.predict(batch.frames))
        return
    with ThreadPoolExecutor(1, thread_name_prefix="evaluation-record") as recorder:
        recording: Optional[Future] = None
        for batch in batches:
            prediction = evaluator.predict(batch.frames)
            if recording is not None:
                recording.result()
            recording = recorder.submit(evaluator.record, batch, prediction)
        if recording is not None:
            recording.result()


def write_tables(folder: Path, frames_table: pd.DataFrame, sequences_table: pd.DataFrame,
                 trajectories: dict) -> None:
    """The per-frame, per-sequence and trajectory tables (CSV) of one test set, the data of its DVC plots."""
    write_csv(folder / "per_frame.csv", frames_table)
    write_csv(folder / "per_sequence.csv", sequences_table)
    rows = [{"sequence": seq, "frame": f, **{f"{m}_{axis}": traj[m][i, k] for m in ("gt", *POSE_METHODS) if m in traj
                                               for k, axis in enumerate("xyz")}}
            for seq, traj in trajectories.items() for i, f in enumerate(traj["frames"])]
    if rows:
        write_csv(folder / "trajectory.csv", pd.DataFrame(rows))


def write_plots(name: str, out_plots: Path, evaluator: SequenceEvaluator, frames_table: pd.DataFrame,
                trajectories: dict) -> None:
    """The PNG figures of one test set (pictures only: DVC shows them offline), swapped in as a whole."""
    with staged_directory(out_plots, FIGURE_FOLDER) as folder:
        for seq, traj in trajectories.items():
            figure = plots.trajectory_figure(f"{name} {seq}: trajectory (scale fitted, chained from the first "
                                             f"GT pose)", traj["gt"], {m: traj[m] for m in POSE_METHODS if m in traj})
            save_figure(folder / f"trajectory_{slug(seq)}.png", figure)
        if evaluator.examples:
            save_figure(folder / "depth_examples.png",
                        plots.depth_examples_figure(f"{name}: depth examples", evaluator.examples))
        curves = {metric: {m: frames_table[f"{key}_{m}"].to_numpy() for m in methods
                           if f"{key}_{m}" in frames_table}
                  for metric, key, methods in (("Abs Rel (paper)", "abs_rel", DEPTH_METHODS),
                                               ("RTE (cm)", "rte", POSE_METHODS),
                                               ("ROT (deg)", "rot", POSE_METHODS))}
        curves = {k: v for k, v in curves.items() if v}
        if curves:
            save_figure(folder / "errors_per_frame.png", plots.error_curves_figure(f"{name}: per-frame errors",
                                                                                   curves))


def log_evaluation(params: Params, project_root: str | Path, result: dict, plots_dir: Path) -> None:
    """Log the headline as metrics (``test/<test set>/<name>``, columns of the runs table), every figure as the
    table ``eval/<test set>/figures.csv`` and the plots into the training run, or into a run opened for the
    model when the store lacks its training run (:func:`tracking.run_for_model`)."""
    run = tracking.run_for_model(params, project_root, result.get("mlflow_run_id"), "evaluate")
    prefix = f"eval/{result['test_set']}"
    headline = mlflow_metrics(result["test_set"], result)
    run.log_metrics(headline)
    run.show_in_runs_table(headline)
    run.log_table(figure_rows(result), f"{prefix}/figures.csv")
    run.log_artifact(plots_dir, prefix)
    test_set = eval_set(params, result["test_set"])
    shards = eval_set_folder(absolute_location(params.eval.shards, project_root), test_set)
    # named after the test set: MLflow keeps one input per name and digest, and the training shards may be
    # the same folder
    run.log_shards_input(manifest_location(shards), result["test_set"], "evaluation")


def run_evaluation(params: Params, name: str, project_root: str | Path = ".") -> dict:
    """The ``evaluate`` stage for test set ``name``: read its shards, evaluate, write outputs, log to MLflow."""
    root = Path(project_root).resolve()
    use_cpu_threads(params.threads)
    urls = eval_set_shards(absolute_location(params.eval.shards, root), eval_set(params, name))
    plots_dir = root / params.eval.plots / name
    model = params.eval.model if is_model_uri(params.eval.model) else root / params.eval.model
    with local_model_file(model, tracking.tracking_uri(params, root)) as model_path:
        result = evaluate_test_set(params, name, urls, model_path,
                                   root / params.eval.metrics / f"{name}.json", plots_dir,
                                   root / params.eval.predictions / name)
    log_evaluation(params, root, result, plots_dir)
    return result
