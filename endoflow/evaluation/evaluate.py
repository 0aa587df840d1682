"""Evaluate a trained model on one test set, with trivial baselines on the same frames in the same run.

Every frame of each test sequence, in order (:mod:`endoflow.data.sequences`), goes through the networks on
``eval.device`` under ``eval.precision``; with ``refine.enabled`` the pose network's path is also refined against
keyframes (:mod:`endoflow.geometry.direct_alignment`) and scored as the method ``refined``. Depth is scored in the
paper's and SimCol3D's protocols beside ``constant_depth`` and ``mean_depth_map``, pose in SimCol3D's, EndoSLAM's
and the motion protocol beside ``constant_velocity``, and the model's scale consistency
(:mod:`endoflow.evaluation.metrics`, :mod:`endoflow.evaluation.baselines`); every figure goes into one long table
(:mod:`endoflow.evaluation.scores`). What is written, with units: docs/outputs.md, "evaluate@<test set>".
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Collection, Iterable, Iterator, Optional

import cv2
import numpy as np
import pandas as pd
import torch

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
from endoflow.data.sequences import FrameRecord, sequence_frames
from endoflow.data.shard_format import has_ground_truth, manifest_location, read_manifest
from endoflow.devices import (autocast, images_to_device, resolve_device, to_compute_layout, unit_float_images,
                              use_cpu_threads)
from endoflow.geometry.direct_alignment import KeyframeTracker, TrackerSettings, tracker_settings
from endoflow.locations import absolute_location
from endoflow.models.endoflow_model import load_trained_model
from endoflow.models.mlflow_model import is_model_uri, local_model_file
from endoflow.models.model_file import TrainingBaselines



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
    # per frame, T_world_cam of the refined path (endoflow.geometry.direct_alignment), from an identity first pose
    refined: list[np.ndarray] = field(default_factory=list)


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
def batches_within_sequences(frames: Iterable[FrameRecord], size: int) -> Iterator[list[FrameRecord]]:
    """Consecutive frames in lists of at most ``size``, never mixing two sequences."""
    batch: list[FrameRecord] = []
    for frame in frames:
        if batch and (len(batch) == size or frame.sequence != batch[0].sequence):
            yield batch
            batch = []
        batch.append(frame)
    if batch:
        yield batch


# ------------------------------------------------------------------------------------- prediction
class SequenceEvaluator:
    """Runs the model over ordered frames, writes challenge predictions and gathers per-sequence results; the
    per-image depth errors go straight into ``scores``, rows of :mod:`endoflow.evaluation.scores`' table."""

    def __init__(self, model: torch.nn.Module, baselines: TrainingBaselines, predictions_dir: Path,
                 device: torch.device, precision: Precision, max_examples: int,
                 refine: Optional[TrackerSettings] = None) -> None:
        self.model = model
        self.refine = refine
        self.tracker: Optional[KeyframeTracker] = None
        self.max_examples = max_examples
        self.baselines = baselines
        self.predictions_dir = predictions_dir
        self.device = device
        self.precision = precision
        self.sequences: list[SequenceResult] = []
        self.scores: list[dict] = []
        self.examples: list[dict] = []
        self._carry: Optional[FrameRecord] = None
        self.frames_done = 0

    @torch.inference_mode()
    def process(self, batch: list[FrameRecord]) -> None:
        """One batch of consecutive frames of one sequence."""
        result = self._sequence_for(batch[0])
        rgb = self._images(batch)
        with autocast(self.device, self.precision):
            depth = self.model.predict_depth(rgb)
        depth = depth[:, 0].float().cpu().numpy()
        earlier = [self._carry] + batch[:-1] if self._carry is not None else batch[:-1]
        later = batch if self._carry is not None else batch[1:]
        relative = np.zeros((0, 4, 4))
        if later:
            source, target = self._images(earlier), self._images(later)
            # T_earlier_later = inv(P_earlier) @ P_later: the challenge's relative pose
            with autocast(self.device, self.precision):
                relative = self.model.predict_pose(target, source, source_is_next=False)
            relative = relative.double().cpu().numpy()
            for first, second, pose in zip(earlier, later, relative):
                if not second.after_gap:  # no challenge pose across missing frames; never scored either
                    self._write_pose(first, second, pose)
                result.predicted_relative.append(pose)
        if self.refine is not None:
            # the step into each frame of the batch; the sequence's first frame has none
            steps = [None] * (len(batch) - len(relative)) + list(relative)
            self._track(result, batch, depth, steps)
        for frame, prediction in zip(batch, depth):
            self._add_frame(result, frame, prediction)
        self._carry = batch[-1]
        self.frames_done += len(batch)

    def _track(self, result: SequenceResult, batch: list[FrameRecord], depth: np.ndarray,
               steps: list[Optional[np.ndarray]]) -> None:
        """Each frame's refined pose, aligned to the tracker's keyframe from the pose network's step; the tracker
        starts anew with each sequence and after missing frames."""
        # the frames as read, not the device's copy (bf16 under autocast on a GPU)
        images = unit_float_images(torch.stack([frame.rgb for frame in batch]))
        for frame, image, prediction, step in zip(batch, images, depth, steps):
            if step is None or frame.after_gap:  # a sequence's K is its own
                self.tracker = KeyframeTracker(self._camera_K(frame), self.refine)
            start = np.eye(4) if step is None else result.refined[-1] @ step
            result.refined.append(self.tracker.track(image, torch.from_numpy(prediction)[None],
                                                     torch.from_numpy(start)).numpy())

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
            self._carry = None
        return self.sequences[-1]

    def _add_frame(self, result: SequenceResult, frame: FrameRecord, prediction: np.ndarray) -> None:
        if frame.after_gap:
            result.gaps.add(len(result.frames))
        result.frames.append(frame.frame)
        result.poses.append(frame.pose)
        result.depth_ratios.append(None)
        self._write_depth(frame, prediction)
        if frame.depth_cm is None:
            return
        result.depth_frames.append(frame.frame)
        result.depth_pred.append(metrics.depth_to_simcol_unit(prediction).astype(np.float16))
        result.depth_gt.append(frame.depth_cm)
        baselines = baseline_depths(self.baselines, frame.depth_cm.shape)
        for method, pred in (("model", prediction), *baselines.items()):
            errors = metrics.paper_depth_errors(frame.depth_cm, pred)
            self.scores += score_rows(frame.sequence, frame.frame, method, "depth_paper", errors)
            if method == "model":
                result.depth_ratios[-1] = errors["ratio"]
        if len(result.depth_frames) == 1 and len(self.examples) < self.max_examples:
            self.examples.append({"label": f"{frame.sequence} #{frame.frame}", "gt": frame.depth_cm,
                                  "rgb": frame.rgb.permute(1, 2, 0).numpy(), "pred": prediction})

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
    for seq in evaluator.sequences:
        rows += depth_sequence_scores(seq, evaluator.baselines)
        pose_rows, trajectory = pose_sequence_scores(seq, evaluator.baselines)
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


def pose_sequence_scores(seq: SequenceResult, training: TrainingBaselines) -> tuple[list[dict], Optional[dict]]:
    """The challenge's, EndoSLAM's and the motion protocols over the longest run of one sequence's posed frames, for
    the model (its network's and its refined path) and constant velocity, and the scale consistency of the model's
    paths where the run has GT depth: the sequence's figures, each frame's RTE and ROT, and the trajectories."""
    run = longest_posed_run(seq.poses, seq.gaps)
    if run is None:
        return [], None
    start, stop = run
    gt_poses = np.stack(seq.poses[start:stop])
    predicted = {"model": np.stack(seq.predicted_relative[start:stop - 1]),
                 **({"refined": metrics.relative_poses(np.stack(seq.refined[start:stop]))} if seq.refined else {}),
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
    ratios = [ratio for ratio in seq.depth_ratios[start:stop] if ratio is not None]
    for method in ("model", "refined") if ratios else ():
        if method in predicted and np.any(predicted[method][:, :3, 3]):
            rows += score_rows(seq.name, None, method, "scale",
                               metrics.scale_consistency(gt_poses, predicted[method], ratios))
    return rows, trajectory


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

    Returns the full result (with ``mlflow_run_id`` of the training run), written to
    ``<out_predictions>/evaluation.json``; ``out_metrics`` gets its headline (:mod:`endoflow.evaluation.results`).
    """
    test_set = eval_set(params, name)
    device = resolve_device(params.eval.device, "eval.device")
    model, record = load_trained_model(model_path, device)
    model = to_compute_layout(model, device, params.eval.precision)
    started = time.perf_counter()
    earlier = marked_output(f"the predictions of test set {name}", EVALUATION_FILE, test_set=name)
    with staged_directory(out_predictions, earlier) as predictions_dir:
        refine = tracker_settings(params.refine) if params.refine.enabled else None
        evaluator = SequenceEvaluator(model, record.baselines, predictions_dir, device, params.eval.precision,
                                      params.eval.depth_examples, refine)
        frames = sequence_frames(urls, lambda meta: belongs_to(meta, test_set),
                                 params.eval.max_frames_per_sequence)
        for batch in batches_within_sequences(frames, params.eval.batch_size):
            evaluator.process(batch)
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
