"""The driver side of training: Ray, the MLflow run, Ray Train's ``TorchTrainer``, and the stage outputs.

Locations (``train.shards``, ``train.latent_bank``, ``ray.storage_path``) may be local paths, made absolute
against the project root because Ray workers run in their own session folders, or fsspec URLs
(``s3://...``, ``file:///...``) that every node of a cluster can reach.

Resuming: the Ray run is named ``<ray.run_name>-<fingerprint>``, where the fingerprint covers every param
that changes what training computes (not ``train.epochs``, so raising it continues a run) and the bytes of
the train manifest and the latent bank. Ray Train restores a run of the same name and storage path from its
latest checkpoint, so re-running an interrupted ``train`` stage continues with the next epoch, while any
change of params or data starts afresh. The driver also looks for the newest complete checkpoint itself
and passes it to the workers (Ray's own record can lag behind a kill); when it already covers
``train.epochs``, Ray is not started and the outputs are rewritten from it. The MLflow run of an unfinished
training is reopened likewise.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import posixpath
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional

import fsspec
import numpy as np
import pandas as pd

from endoflow import tracking
from endoflow.config import ConfigError, Params, flatten_params, training_keys
from endoflow.data.loader import batch_shares, list_shards, raw_samples
from endoflow.data.shard_format import (
    DEPTH_MEMBER,
    META_MEMBER,
    decode_depth,
    decode_meta,
    manifest_location,
)
from endoflow.errors import DataFormatError
from endoflow.evaluation import plots
from endoflow.geometry.pose import mean_step, step_root
from endoflow.io import (
    FIGURE_FOLDER,
    file_sha256,
    owned_prefix,
    remove_abandoned,
    save_figure,
    staged_directory,
    write_csv,
    write_json,
)
from endoflow.locations import absolute_location, home_project, local_file
from endoflow.models.depth_range import COLLAPSED_SHARE
from endoflow.models.mlflow_model import log_mlflow_model
from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
from endoflow.models.latent_bank import check_latent_bank_file
from endoflow.ray_runtime import connect_ray, ray_train_settings, worker_logs_to
from endoflow.training.checkpoint import TrainingCheckpoint, TrainState, latest_checkpoint, load_training_state
from endoflow.training.worker_config import WorkerConfig

class TrainingError(RuntimeError):
    """Training failed on the workers; the message carries the workers' own error."""


# A full disk or quota, a read-only file system, missing permission: a rerun fails the same way until fixed.
REPEATING_OS_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})


# what ``train.metrics`` holds for DVC, under ``train``: {name with its unit: key of the training summary} (the
# other figures, the run id and fingerprint are in the model file and the MLflow run)
TRAIN_DVC_METRICS = {"best_epoch": "best_epoch", "val_abs_rel": "val_abs_rel", "val_rmse_cm": "val_rmse",
                     "val_photometric": "val_photometric"}
# the best epoch's validation figures in the closing lines, as a person reads them
VALIDATION_LABELS = {"val_abs_rel": "val Abs Rel", "val_rmse": "val RMSE (cm)",
                     "val_photometric": "val photometric error of held-out frames"}
# the training summary (the best epoch's figures, steps, run id, fingerprint) in the MLflow run
TRAINING_SUMMARY_ARTIFACT = "train/summary.json"
# every line Ray's processes printed while training (the terminal shows those that matter), in the MLflow run
# as logs/ray-from-epoch-NNNN.log, one file per attempt (a resumed training adds one)
RAY_LOG_FOLDER = "logs"
# the temporary folder an attempt's Ray log is written to before it is uploaded
RAY_LOG_TEMPORARY = "endoflow-ray-log-"


def training_fingerprint(params: Params, train_shards: str | list[str], latent_bank: Optional[str]) -> str:
    """SHA-256 (hex, 16 chars) of the params that shape training and of the train manifests (of ``train_shards``,
    one folder or several) and latent bank."""
    digest = hashlib.sha256()
    shaping = set(training_keys(params))
    flat = {k: v for k, v in flatten_params(params).items() if k in shaping or k.rpartition(".")[0] in shaping}
    digest.update(json.dumps(flat, sort_keys=True, default=str).encode())
    folders = [train_shards] if isinstance(train_shards, str) else train_shards
    for location in [*map(manifest_location, folders), *([latent_bank] if latent_bank else [])]:
        with fsspec.open(location, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()[:16]


def training_baselines(train_urls: list[str]) -> TrainingBaselines:
    """Mean GT depth (scalar and per pixel) and mean per-frame relative pose of the train shards' samples that have
    them (depth NaN, the step the identity, where none has).

    A sample's ``inv(T_cur) @ T_next`` spans its ``neighbour_offset`` frames (``meta.json``); its per-frame root
    (:func:`step_root`) is what the constant-velocity baseline repeats between consecutive frames.
    """
    depth_sum: Optional[np.ndarray] = None
    depth_count: Optional[np.ndarray] = None
    steps: dict[int, list[np.ndarray]] = {}
    for sample in raw_samples(train_urls):
        meta = decode_meta(sample[META_MEMBER], sample["__url__"])
        depth = decode_depth(sample[DEPTH_MEMBER], meta["depth_unit"], sample["__url__"]).astype(np.float64)
        if depth_sum is None:
            depth_sum, depth_count = np.zeros_like(depth), np.zeros_like(depth)
        if depth.shape == depth_sum.shape:
            depth_sum += depth
            depth_count += depth > 0
        poses = meta["T_world_cam"]
        if poses.get("cur") is not None and poses.get("next") is not None:
            relative = np.linalg.inv(np.array(poses["cur"])) @ np.array(poses["next"])
            steps.setdefault(int(meta["neighbour_offset"]), []).append(relative)
    if depth_sum is None:
        raise ValueError(f"train shards {train_urls[:1]}...: no samples to compute the baselines from")
    # unlabelled video alone: no depth baselines (NaN, shown as such), the identity step
    mean_depth = float(depth_sum.sum() / depth_count.sum()) if depth_count.sum() else math.nan
    mean_map = np.where(depth_count > 0, depth_sum / np.maximum(depth_count, 1), mean_depth)
    per_frame = [step_root(np.array(spanned), offset) for offset, spanned in sorted(steps.items())]
    return TrainingBaselines(mean_depth, mean_map.astype(np.float32),
                             mean_step(np.concatenate(per_frame) if per_frame else np.zeros((0, 4, 4))))


def intrinsics_to_learn(train_urls: list[str]) -> dict[str, list[list[float]]]:
    """Each dataset of the train shards that has samples with an unknown K (a camera nobody calibrated, or K
    withheld), with the assumed K (stored size) of its first such sample."""
    found: dict[str, list[list[float]]] = {}
    for sample in raw_samples(train_urls):
        meta = decode_meta(sample[META_MEMBER], sample["__url__"])
        if not meta["intrinsics_known"]:
            found.setdefault(meta["dataset"], meta["K"])
    return found


def train(params: Params, project_root: str | Path = ".") -> dict[str, Any]:
    """Run the ``train`` stage: Ray training, then the model file, metrics and plots. Returns the metrics.

    Inputs are checked before Ray starts (shards listed in their manifests, the latent bank readable); any
    failure after the MLflow run is opened marks it FAILED, an interrupt KILLED (a rerun with the same inputs
    reopens it).
    """
    root = Path(project_root).resolve()
    folders = [absolute_location(folder, root) for folder in (params.train.shards, *params.train.mix)]
    train_urls = [list_shards(folder, "train") for folder in folders]
    val_urls = [url for folder in folders for url in list_shards(folder, "val")]
    for folder, urls in zip(folders, train_urls):
        if not urls:
            raise FileNotFoundError(f"{folder}: no train-*.tar shards (run the preprocess stage first)")
    shares = mix_shares(params)
    latent_bank = absolute_location(params.train.latent_bank, root) if params.model.latent_bank else None
    if latent_bank:
        check_latent_bank_file(local_file(latent_bank))
    fingerprint = training_fingerprint(params, folders, latent_bank)
    name = tracking.run_name_for("train", [*tracking.ablation_switches(params), f"seed{params.seed}"])
    with tracking.run(params, root, params.tracking.experiment, name, fingerprint) as run:
        for folder in folders:
            run.log_shards_input(manifest_location(folder), posixpath.basename(folder.rstrip("/")), "training")
        if latent_bank:
            tracking.link_latent_bank(params, run, file_sha256(latent_bank))
        # the run crosses to the Ray workers by its id
        config = WorkerConfig(params, tuple(map(tuple, train_urls)), tuple(val_urls), latent_bank, run.uri,
                              run.run_id, resume_from=None, unlogged_metrics=str(run.unlogged_file()),
                              batch_shares=tuple(shares),
                              learn_intrinsics=intrinsics_to_learn([u for urls in train_urls for u in urls]))
        return train_in_run(params, root, run, config, fingerprint)


def mix_shares(params: Params) -> list[int]:
    """Samples of every batch that ``train.shards`` (weight 1) and each folder of ``train.mix`` give.

    Raises:
        ConfigError: a folder would give none (naming it, and what to change).
    """
    folders = [params.train.shards, *params.train.mix]
    shares = batch_shares(params.train.batch_size, [1.0, *params.train.mix.values()])
    for folder, share in zip(folders, shares):
        if share == 0:
            raise ConfigError(f"train.mix: {folder} would give 0 of the {params.train.batch_size} samples of a batch; "
                              f"raise its weight or train.batch_size")
    return shares


def train_in_run(params: Params, root: Path, run: tracking.RunHandle, config: WorkerConfig,
                 fingerprint: str) -> dict[str, Any]:
    """Train (or resume) on Ray and write the outputs, inside the open MLflow ``run`` (``config``'s)."""
    baselines = training_baselines(list(config.all_train_shards))
    storage = absolute_location(params.ray.storage_path, home_project(root))
    run_name = f"{params.ray.run_name}-{fingerprint}"
    resume_from = latest_checkpoint(f"{storage.rstrip('/')}/{run_name}", params.ray.num_workers)
    saved = load_training_state(resume_from) if resume_from else None
    if saved is not None:
        print(f"[train] resuming after epoch {saved.state.epoch + 1} from {resume_from}", flush=True)
    if saved is None or saved.state.epoch + 1 < params.train.epochs:
        remove_abandoned(tempfile.gettempdir(), RAY_LOG_TEMPORARY)  # the folders of killed trainings
        with tempfile.TemporaryDirectory(prefix=owned_prefix(RAY_LOG_TEMPORARY)) as folder:
            ray_log = Path(folder) / f"ray-from-epoch-{(saved.state.epoch + 2 if saved else 1):04d}.log"
            try:
                saved = fit_on_ray(params, replace(config, resume_from=resume_from), storage, run_name, ray_log)
            except ConfigError:
                raise  # a setting the cluster cannot hold: rerunning would not help, the message names the key
            except Exception as exc:
                raise TrainingError(training_failure(exc, storage)) from exc
            finally:
                log_ray_lines(run, ray_log)
    summary = write_training_outputs(params, root, saved.state, run.run_id, baselines, fingerprint)
    # one-off figures: an artifact, not single-point charts above the run's curves
    run.log_dict(summary, TRAINING_SUMMARY_ARTIFACT)
    model_file, registered = root / params.train.out, params.tracking.registered_model
    run.best_effort("the MLflow model", lambda: log_mlflow_model(run.uri, run.run_id, model_file, registered))
    run.log_artifact(root / params.train.plots, "plots/train")
    return summary


def format_training_summary(summary: dict[str, Any], model_path: str) -> str:
    """The closing lines of the ``train`` stage: the best epoch's validation figures, the model and the run."""
    figures = "; ".join(f"{label} {summary[key]:.4f}" for key, label in VALIDATION_LABELS.items() if key in summary)
    return (f"[train] done: {summary['epochs']} epochs, {summary['global_steps']} steps; best epoch "
            f"{summary['best_epoch']}{': ' + figures if figures else ' (no validation data)'}; final train loss "
            f"{summary['final_train_loss']:.4f}\n"
            f"[train] model written to {model_path}; MLflow run {summary['mlflow_run_id']}\n")


def depth_collapse_warning(summary: dict[str, Any]) -> str | None:
    """A warning naming the epochs of a training ``summary`` whose validation depth collapsed
    (``depth_collapsed_epochs``) and whether the model file, the best epoch's, is one of them; None if none did."""
    epochs, best_epoch = summary.get("depth_collapsed_epochs", []), summary["best_epoch"]
    if not epochs:
        return None
    model = ("the model file's depth is one of them" if best_epoch in epochs
             else f"the model file is epoch {best_epoch}'s, whose validation depth had not")
    return (f"after epoch{'s' if len(epochs) > 1 else ''} {epoch_ranges(epochs)} {COLLAPSED_SHARE:.0%} of the "
            f"validation depth or more sat at an end of its range (model.min_depth, model.max_depth): the depth "
            f"network collapsed to the photometric loss's degenerate answer; {model} (training with loss.automask "
            f"on, the default, guards against it)")


def epoch_ranges(epochs: list[int]) -> str:
    """``[2, 3, 4, 7]`` -> ``"2-4, 7"``."""
    runs: list[list[int]] = []
    for epoch in sorted(epochs):
        if runs and epoch == runs[-1][-1] + 1:
            runs[-1].append(epoch)
        else:
            runs.append([epoch])
    return ", ".join(f"{run[0]}-{run[-1]}" if len(run) > 1 else f"{run[0]}" for run in runs)


def log_ray_lines(run: tracking.RunHandle, ray_log: Path) -> None:
    """Upload the attempt's Ray log into the run; a failed upload is a warning, never the training's outcome."""
    if not ray_log.exists():
        return
    try:
        run.log_artifact(ray_log, RAY_LOG_FOLDER)
    except Exception as exc:  # the training's own result or error is what the caller must see
        print(f"[train] warning: Ray's log {ray_log.name} was not logged to MLflow: {exc}", file=sys.stderr)


def fit_on_ray(params: Params, config: WorkerConfig, storage: str, run_name: str,
               ray_log: Path) -> TrainingCheckpoint:
    """Train with Ray Train's ``TorchTrainer`` (DDP); returns the final training state. Every line Ray's
    processes print is appended to ``ray_log`` (the terminal gets those that matter, see
    :func:`endoflow.ray_runtime.worker_logs_to`).

    Ray keeps the newest ``train.keep_checkpoints`` checkpoints (each carries the best epoch's weights). When a
    worker fails (its process or node lost, or an error), Ray Train restarts every worker, up to
    ``ray.max_failures`` times, and they continue after the newest checkpoint it recorded (see
    :func:`endoflow.training.loop.restored_checkpoint`).
    """
    from ray.train import CheckpointConfig, FailureConfig, LoggingConfig, RunConfig
    from ray.train.torch import TorchTrainer

    from endoflow.training.cluster import check_worker_resources, scaling_config
    from endoflow.training.loop import train_loop_per_worker

    started_ray = connect_ray(params.ray)
    try:
        check_worker_resources(params.ray)
        trainer = TorchTrainer(
            train_loop_per_worker,
            train_loop_config=config,
            scaling_config=scaling_config(params.ray),
            run_config=RunConfig(name=run_name, storage_path=storage,
                                 failure_config=FailureConfig(max_failures=params.ray.max_failures),
                                 checkpoint_config=CheckpointConfig(num_to_keep=params.train.keep_checkpoints),
                                 # Ray Train's INFO lines (each checkpoint and report, worker start-up) go to
                                 # its log files in the Ray session folder only; our progress lines stay
                                 logging_config=LoggingConfig(log_level="WARNING")),
        )
        with worker_logs_to(ray_log), ray_train_settings(params.ray):
            result = trainer.fit()
    finally:
        if started_ray:
            import ray

            ray.shutdown()
    if result.checkpoint is None:
        raise TrainingError("training finished without a checkpoint (train.epochs must be at least 1)")
    with result.checkpoint.as_directory() as folder:
        return load_training_state(folder)


def training_failure(exc: BaseException, storage: str) -> str:
    """What the user reads when training fails: the first worker's own error, and what to do about it."""
    cause = worker_cause(exc)
    return f"training failed: {type(cause).__name__}: {cause}{next_step(cause, storage)}"


def worker_cause(exc: BaseException) -> BaseException:
    """The first worker's own error when Ray wraps it, else ``exc``."""
    failures = getattr(exc, "worker_failures", None)
    if failures:
        first = failures[min(failures)]
        return getattr(first, "cause", None) or first
    return exc


def next_step(cause: BaseException, storage: str) -> str:
    """Advice to rerun the stage only where a rerun can help (a lost worker, node or connection): it resumes
    from the last checkpoint and meets an error of the data, the disk or the computation again."""
    if isinstance(cause, DataFormatError):
        return f" (a rerun repeats this until {cause.path} is rebuilt or removed)"
    if isinstance(cause, OSError) and cause.errno in REPEATING_OS_ERRORS:
        return (f" (a rerun repeats this until the disk or its permissions are fixed; training writes checkpoints "
                f"to ray.storage_path {storage}; then rerun the stage to resume from the last checkpoint)")
    if getattr(cause, "rerun_repeats", False):
        return ""  # its message says what to change
    return " (rerun the stage to resume from the last checkpoint)"


def write_training_outputs(params: Params, root: Path, state: TrainState, run_id: str,
                           baselines: TrainingBaselines, fingerprint: str) -> dict[str, Any]:
    """``train.out`` (best epoch's weights), ``train.metrics`` and ``train.plots`` from the final state."""
    best = state.best
    best_epoch = int(best.epoch) + 1  # counted from 1, as the history and progress lines count
    save_model_file(root / params.train.out, ModelRecord(params=params, state=best.model, epoch=best_epoch,
                                                         val=best.val, mlflow_run_id=run_id, baselines=baselines))
    history = pd.DataFrame(state.history)
    with staged_directory(root / params.train.plots, FIGURE_FOLDER) as folder:
        write_csv(folder / "history.csv", history)
        keys = [k for k in ("train_loss", "val_abs_rel", "val_rmse", "val_photometric", "lr") if k in history]
        save_figure(folder / "curves.png", plots.training_curves_figure(state.history, keys))
    best_row = next((row for row in state.history if row["epoch"] == best_epoch), {})
    summary = {
        "epochs": int(state.epoch) + 1,
        "global_steps": int(state.global_step),
        "best_epoch": best_epoch,
        **{k: float(v) for k, v in best.val.items()},
        # the intrinsics the model learned, where some camera's K was unknown
        **{k: float(v) for k, v in best_row.items() if k.startswith("intrinsics/")},
        "final_train_loss": float(state.history[-1]["train_loss"]),
        "depth_collapsed_epochs": depth_collapsed_epochs(state.history),
        "mlflow_run_id": run_id,
        "fingerprint": fingerprint,
    }
    write_json(root / params.train.metrics, train_dvc_metrics(summary))
    return summary


def depth_collapsed_epochs(history: list[dict[str, Any]]) -> list[int]:
    """The epochs (from 1) after which :data:`~endoflow.models.depth_range.COLLAPSED_SHARE` of the validation depth
    or more sat at an end of its range (:mod:`endoflow.models.depth_range`)."""
    return [int(row["epoch"]) for row in history if row.get("val_depth_at_range_ends", 0.0) >= COLLAPSED_SHARE]


def train_dvc_metrics(summary: dict[str, Any]) -> dict[str, dict[str, float]]:
    """The content of ``train.metrics``: :data:`TRAIN_DVC_METRICS` of the training summary that has them."""
    return {"train": {name: summary[key] for name, key in TRAIN_DVC_METRICS.items() if key in summary}}
