"""``endoflow adapt``: a trained model fitted to one video by self-supervised fine-tuning, in one process.

The video's frames (a range, every ``stride``-th) are split by time: the last ``held_out`` share is never trained on,
and the photometric error of rebuilding those frames from their neighbours
(:func:`~endoflow.losses.photometric.held_out_photometric_error`) is measured before and after. Training draws
``batch_size`` consecutive triplets at random (seeded) from the rest for ``steps`` steps with the model's own
objective, field of view and loss settings, at a constant learning rate. A camera whose intrinsics are unknown
starts from what the model learned for its camera (or the assumed K) and goes on learning them on the video. The
result is a model file whose ``adapted_from`` names its parent, and an MLflow model in a run tagged with the
parent's run. docs/adapt.md says more.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from endoflow.config import DATASETS, Params
from endoflow.data.base import Sequence
from endoflow.data.crop import Crop
from endoflow.data.field_of_view import resized_field_of_view
from endoflow.data.frame_encoding import resize_rgb, stored_intrinsics
from endoflow.data.intrinsics import check_intrinsics, read_intrinsics
from endoflow.data.registry import open_reader
from endoflow.data.video import video_sequence
from endoflow.devices import images_to_device, resolve_device, to_compute_layout, use_cpu_threads
from endoflow.errors import DataFormatError
from endoflow.io import file_sha256
from endoflow.losses.photometric import held_out_photometric_error
from endoflow.models.endoflow_model import EndoflowModel, load_trained_model
from endoflow.models.model_file import ModelRecord, load_model_file, save_model_file
from endoflow.progress import Progress
from endoflow.training.objective import loss_weights, training_step_losses
from endoflow.training.optimization import make_optimizer

if TYPE_CHECKING:  # MLflow takes seconds to import: only runs that log pay for it
    from endoflow.tracking import RunHandle

MIN_FRAMES = 3  # a triplet
# Fine-tuning starts Adam's moments afresh, so its first steps move every weight by about the learning rate whatever
# its gradient. At the peak rate of training (train.lr) 300 steps on the real clip flattened the default model's
# depth; a tenth of it, about where the cosine schedule ends, lowered the held-out error most of 2e-4, 5e-5 and 2e-5
# (docs/results.md). The learned intrinsics keep train.intrinsics_lr: an assumed focal length can be far off.
LR_SHARE = 0.1
EVAL_BATCH = 16


@dataclass(frozen=True)
class AdaptOptions:
    """``steps`` of ``batch_size`` triplets (None: the model's ``train.batch_size``) at ``lr`` (None:
    :data:`LR_SHARE` of the model's ``train.lr``); frames ``start, start + stride, ...`` below ``stop`` (None: to
    the end), of which the last ``held_out`` share is held out; ``seed`` (None: the model's) fixes the draw;
    ``device``: ``auto``, ``cpu``, ``cuda``."""

    steps: int = 300
    batch_size: Optional[int] = None
    lr: Optional[float] = None
    start: int = 0
    stop: Optional[int] = None
    stride: int = 1
    held_out: float = 0.2
    seed: Optional[int] = None
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.steps < 0 or not 0 < self.held_out < 1 or self.stride < 1 or self.start < 0:
            raise ValueError(f"adapt needs steps >= 0, 0 < held_out < 1, stride >= 1 and start >= 0; got steps="
                             f"{self.steps}, held_out={self.held_out}, stride={self.stride}, start={self.start}")
        if self.lr is not None and not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"--lr must be a positive number, got {self.lr}")
        if self.batch_size is not None and self.batch_size < 1:
            raise ValueError(f"--batch-size must be at least 1, got {self.batch_size}")


# ------------------------------------------------------------------------------------------------ input
def input_sequence(source: Path, sequence: Optional[str], params: Params, crop: Optional[Crop] = None,
                   intrinsics: Optional[str] = None, pattern: Optional[str] = None) -> Sequence:
    """What to adapt to: a video file or a folder of frames (read as the video dataset reads them, cut to ``crop``),
    or the sequence ``sequence`` of a dataset root (its ground truth unused). ``intrinsics`` (a file or
    ``fx,fy,cx,cy`` in pixels of the native frames, :mod:`endoflow.data.intrinsics`) replaces the input's own, a
    sidecar's or the assumed K. ``pattern`` (a glob such as ``*_color.png``) picks a folder's frames, as
    ``reconstruct --pattern`` does."""
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such video, image folder or dataset root")
    if pattern is not None and sequence is not None:
        raise DataFormatError(source, f"--pattern {pattern!r} picks images of a folder, not a dataset sequence")
    if sequence is None:
        video = params.data.video.replace(crop=[crop.x, crop.y, crop.width, crop.height] if crop else None, fps=None)
        return video_sequence(source, video, params.data.assumed_fov_deg, intrinsics, pattern)
    if crop is not None:
        raise DataFormatError(source, "--crop cuts a video or a folder of frames, not a dataset sequence")
    found = [s for s in open_reader(source, None, params).sequences() if s.name == sequence]
    if not found:
        raise DataFormatError(source, f"no sequence {sequence!r}")
    chosen = found[0]
    if intrinsics is not None:
        K = read_intrinsics(intrinsics, chosen.image_size)
        check_intrinsics(K, chosen.image_size, intrinsics)
        chosen.K, chosen.intrinsics_known = K, True
    return chosen


def fits_better(summary: dict) -> bool:
    """Whether an adaptation (its :func:`adapt` summary) explains the held-out frames better than the model it
    started from: the one sign without ground truth that it helped. Where it does not, says so: ``reconstruct``
    then keeps the model as trained."""
    before, after = summary["held_out_photometric_before"], summary["held_out_photometric_after"]
    if after < before:  # False for a NaN either side
        return True
    print(f"[adapt] warning: the adapted model does not explain the held-out frames better than the model as "
          f"trained (photometric error {before:.4f} -> {after:.4f}); reconstructing with the model as trained",
          file=sys.stderr)
    return False


def adapt_to_reconstruct_sequence(params: Params, name: str, model_path: Path, out_path: Path,
                                  project_root: str | Path = ".") -> dict:
    """The ``reconstruct`` stage's ``reconstruct.adapt``: the model at ``model_path`` fitted to the frames of
    ``reconstruct.sequences.<name>`` for that many steps, as ``endoflow reconstruct --sequence --adapt`` fits it
    (the sequence read with the model's params, its ground truth unused), written to ``out_path``."""
    cfg = params.reconstruct
    item = cfg.sequences[name]
    root = Path(project_root).resolve()
    use_cpu_threads(params.threads)  # the stage's count, as for its reconstruction: the same model on any machine
    sequence = input_sequence(root / getattr(params.data, item.dataset).root, item.sequence,
                              load_model_file(model_path).params)
    return adapt(sequence, model_path, out_path, AdaptOptions(steps=cfg.adapt, start=item.start, stop=item.stop,
                                                              stride=item.stride, device=cfg.device))


# -------------------------------------------------------------------------------------------- the frames
@dataclass
class Frames:
    """The selected frames at the model's size: ``rgb [N, 3, S, S]`` uint8, the field of view ``valid [1, S, S]``,
    ``K [3, 3]`` (stored size), the camera (a position in DATASETS) and whether its K is known."""

    rgb: torch.Tensor
    valid: torch.Tensor
    K: torch.Tensor
    camera: int
    intrinsics_known: bool

    def batch(self, targets: torch.Tensor, device: torch.device) -> dict[str, torch.Tensor]:
        """The triplets around ``targets`` (positions of ``cur``) as a loader batch on ``device``."""
        count = len(targets)
        batch = {name: images_to_device(self.rgb[targets + shift], device, "float32")
                 for name, shift in (("prev", -1), ("cur", 0), ("next", 1))}
        batch.update(K=self.K.expand(count, 3, 3).to(device), valid=self.valid.expand(count, 1, *self.valid.shape[-2:])
                     .to(device), camera=torch.full((count,), self.camera, device=device),
                     intrinsics_known=torch.full((count,), self.intrinsics_known, device=device))
        return batch


def load_frames(sequence: Sequence, positions: list[int], size: int) -> Frames:
    """The frames at ``positions`` of ``sequence``, resized as preprocessing resizes them, with the sequence's field
    of view and K."""
    progress = Progress(len(positions), "frames")
    images = []
    for done, position in enumerate(positions, 1):
        images.append(torch.from_numpy(resize_rgb(sequence.load_rgb(position), size)).permute(2, 0, 1))
        if done % 100 == 0:
            print(f"[adapt] reading {progress.update(done)}", file=sys.stderr)
    valid = resized_field_of_view(sequence.field_of_view(), size)
    K = stored_intrinsics(sequence.K, sequence.image_size, size)
    return Frames(torch.stack(images), torch.from_numpy(valid)[None], torch.from_numpy(K).float(),
                  DATASETS.index(sequence.dataset), sequence.intrinsics_known)


# ------------------------------------------------------------------------------------------------- adapt
def adapt(sequence: Sequence, model_path: Path, out_path: Path, options: AdaptOptions,
          run: Optional["RunHandle"] = None) -> dict:
    """Fit the model of ``model_path`` to ``sequence`` (module docstring) and write the adapted model file to
    ``out_path``; returns the summary (also in the model file's ``adapted_from``). ``run``: the MLflow run to log
    the steps' losses and the figures to."""
    if out_path.resolve() == Path(model_path).resolve():
        raise ValueError(f"--out {out_path} is the model adapted: write the adapted model to another file")
    device = resolve_device(options.device, "--device")
    model, record = load_trained_model(model_path, device)
    params = record.params
    size = params.data.size
    model = to_compute_layout(model, device, "float32", size)
    positions = list(range(options.start, min(options.stop or len(sequence), len(sequence)), options.stride))
    kept = kept_frames(len(positions), options.held_out)
    held_out = len(positions) - kept
    if kept < MIN_FRAMES:
        raise DataFormatError(sequence.name, f"{len(positions)} frames selected: adapting needs at least "
                                             f"{held_out + MIN_FRAMES} ({MIN_FRAMES} to train on, {held_out} held out)")
    frames = load_frames(sequence, positions, size)
    train_targets = torch.arange(1, kept - 1)
    held_out_targets = torch.arange(kept + 1, len(positions) - 1)
    before = held_out_error(model, frames, held_out_targets, device)
    print(f"[adapt] {sequence.name}: {len(positions)} frames at {size} px, training on the first {kept}, holding "
          f"out the last {held_out}; intrinsics {intrinsics_note(model, frames, size)}; held-out photometric error "
          f"before: {before:.4f}", file=sys.stderr)
    losses = fine_tune(model, frames, train_targets, options, params, device, run)
    after = held_out_error(model, frames, held_out_targets, device)
    summary = {
        "parent": {"model": str(model_path), "sha256": file_sha256(model_path), "mlflow_run_id": record.mlflow_run_id},
        "input": sequence.name, "frames": len(positions), "held_out_frames": held_out, "size": size,
        "steps": options.steps, "batch_size": options.batch_size or params.train.batch_size,
        "lr": adapt_lr(options, params), "seed": params.seed if options.seed is None else options.seed,
        "held_out_photometric_before": before, "held_out_photometric_after": after,
        "final_loss": losses[-1] if losses else None, "intrinsics": learned_K_rows(model, frames, size),
    }
    save_model_file(out_path, ModelRecord(
        params=params, state={k: v.detach().cpu() for k, v in model.state_dict().items()}, epoch=record.epoch,
        val={"val_photometric": after}, mlflow_run_id=run.run_id if run is not None else record.mlflow_run_id,
        baselines=record.baselines, adapted_from=summary))
    change = (after - before) / before if before else 0.0
    print(f"[adapt] held-out photometric error {before:.4f} -> {after:.4f} ({change:+.1%}); adapted model written to "
          f"{out_path}", file=sys.stderr)
    return summary


def fine_tune(model: EndoflowModel, frames: Frames, targets: torch.Tensor, options: AdaptOptions, params: Params,
              device: torch.device, run: Optional["RunHandle"]) -> list[float]:
    """``options.steps`` optimiser steps on triplets drawn (seeded) from ``targets``; returns each step's loss."""
    cfg = params.train.replace(lr=adapt_lr(options, params))
    batch_size = min(options.batch_size or cfg.batch_size, len(targets))
    learn_K = not frames.intrinsics_known
    model.intrinsics.learn(learn_K, params.train.intrinsics_principal_point)
    network = [p for name, p in model.named_parameters() if p.requires_grad and not name.startswith("intrinsics.")]
    optimizer = make_optimizer(network, cfg, list(model.intrinsics.parameters()) if learn_K else [])
    generator = torch.Generator().manual_seed(params.seed if options.seed is None else options.seed)
    torch.manual_seed(params.seed if options.seed is None else options.seed)  # the pose samples, the tie-breaks
    logged = ("total", *loss_weights(params.loss))
    progress = Progress(options.steps, "steps")
    losses: list[float] = []
    model.train()
    for step in range(1, options.steps + 1):
        chosen = targets[torch.randperm(len(targets), generator=generator)[:batch_size]]
        out = training_step_losses(model, frames.batch(chosen, device), params.loss)
        if not torch.isfinite(out["total"]):
            raise FloatingPointError(f"non-finite loss at step {step}: lower --lr")
        optimizer.zero_grad(set_to_none=True)
        out["total"].backward()
        optimizer.step()
        losses.append(float(out["total"].detach()))
        if run is not None:
            run.log_metrics({f"loss/{k}": float(out[k].detach()) for k in logged}, step=step)
        if step % max(1, options.steps // 10) == 0 or step == options.steps:
            print(f"[adapt] step {progress.update(step)} | loss {np.mean(losses[-10:]):.4f}", file=sys.stderr)
    model.eval()
    return losses


def kept_frames(count: int, held_out: float) -> int:
    """How many of ``count`` selected frames are trained on: all but the last ``held_out`` share (at least a
    triplet's :data:`MIN_FRAMES` held out)."""
    return count - max(MIN_FRAMES, math.ceil(count * held_out))


def adapt_lr(options: AdaptOptions, params: Params) -> float:
    """The learning rate of the adaptation: ``options.lr``, else :data:`LR_SHARE` of the model's ``train.lr``."""
    return options.lr or params.train.lr * LR_SHARE


@torch.no_grad()
def held_out_error(model: EndoflowModel, frames: Frames, targets: torch.Tensor, device: torch.device) -> float:
    """Mean photometric error of rebuilding the ``targets`` from their neighbours (the held-out measure)."""
    model.eval()
    errors = []
    for start in range(0, len(targets), EVAL_BATCH):
        batch = frames.batch(targets[start:start + EVAL_BATCH], device)
        depth = model.predict_depth(batch["cur"])
        poses = [model.predict_pose(batch["cur"], batch["prev"], source_is_next=False),
                 model.predict_pose(batch["cur"], batch["next"], source_is_next=True)]
        errors.append(held_out_photometric_error(batch["cur"], [batch["prev"], batch["next"]], depth, poses,
                                                 model.camera_K(batch), batch["valid"]))
    return float(torch.cat(errors).mean()) if errors else math.nan


def intrinsics_note(model: EndoflowModel, frames: Frames, size: int) -> str:
    """Which intrinsics the adaptation starts from, in words."""
    if frames.intrinsics_known:
        return "given"
    name = DATASETS[frames.camera]
    start = "the model's learned" if model.intrinsics.learned(frames.camera) else "the assumed"
    return f"unknown: learned on the video, starting from {start} {name!r} camera"


def learned_K_rows(model: EndoflowModel, frames: Frames, size: int) -> list[list[float]]:
    """The K (stored size) the adapted model uses for the video."""
    K = frames.K.to(model.intrinsics.corrections.device)
    if not frames.intrinsics_known:
        K = model.learned_K(DATASETS[frames.camera], K, (size, size))
    return K.detach().cpu().double().tolist()


def log_adaptation(run: "RunHandle", summary: dict, out_path: Path) -> None:
    """The adaptation's figures, its summary and the adapted model (an MLflow model of the run) in ``run``; the run
    names its parent's (:data:`~endoflow.tracking.PARENT_RUN_TAG`)."""
    from endoflow import tracking
    from endoflow.models.mlflow_model import log_mlflow_model

    parent = summary["parent"]["mlflow_run_id"]
    if parent:
        run.set_tags({tracking.PARENT_RUN_TAG: parent})
    run.log_params({"adapt.input": summary["input"], "adapt.steps": str(summary["steps"]),
                    "adapt.lr": str(summary["lr"]), "adapt.frames": str(summary["frames"])})
    run.log_metrics({"held_out_photometric_before": summary["held_out_photometric_before"],
                     "held_out_photometric_after": summary["held_out_photometric_after"]}, step=summary["steps"])
    run.log_dict(summary, "adapt/summary.json")
    run.best_effort("the adapted MLflow model", lambda: log_mlflow_model(run.uri, run.run_id, out_path, None))
