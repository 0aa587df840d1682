"""The per-worker training loop that Ray Train runs on every rank (DDP); it lives in the package because Ray
workers unpickle it by module path, and its one input is a :class:`WorkerConfig`.

Every rank trains on its own shards, the same number of batches each (:func:`endoflow.data.loader.rank_batches`),
so no rank waits forever in an all-reduce; a non-finite loss stops every rank at the same step before any weight
is touched. After each epoch the ranks validate disjoint parts of the val split and every rank reports a
checkpoint (:mod:`endoflow.training.checkpoint`) with its random state, so a resumed run computes the same weights
as an uninterrupted one. Only rank 0 writes to MLflow. docs/architecture.md and docs/cluster.md say more.
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np
import ray.train
import ray.train.torch
import torch
import torch.distributed as dist
from torch import nn

from endoflow.config import Params, Precision, TrainConfig
from endoflow.data.loader import batches_per_epoch, mixed_rank_batches, rank_batches, triplet_dataset
from endoflow.data.shard_format import ShardEntry, shard_entries
from endoflow.devices import (
    autocast,
    batch_to_device,
    compiled,
    images_to_device,
    to_compute_layout,
    use_cpu_threads,
)
from endoflow.evaluation import metrics
from endoflow.locations import local_file
from endoflow.models.depth_range import at_depth_range_ends
from endoflow.models.endoflow_model import EndoflowModel, build_model
from endoflow.progress import Progress
from endoflow.training.checkpoint import (
    BestEpoch,
    TrainingCheckpoint,
    TrainState,
    load_random_state,
    load_training_state,
    restore_random_state,
    save_random_state,
    save_training_state,
    weights_digest,
    write_rank_audit,
)
from endoflow.losses.photometric import held_out_photometric_error
from endoflow.training.objective import loss_weights, training_step_losses
from endoflow.training.optimization import make_optimizer, make_scheduler, restore_scheduler
from endoflow.training.worker_config import WorkerConfig

if TYPE_CHECKING:
    from endoflow import tracking


class NonFiniteLossError(RuntimeError):
    """The training loss became NaN or infinite; the message names the epoch and step and what to change."""

    rerun_repeats = True  # resumed from the last checkpoint, training computes the same loss again


@dataclass(frozen=True)
class EpochContext:
    """What one rank's training needs every epoch."""

    config: WorkerConfig
    module: nn.Module
    model: EndoflowModel
    optimizer: torch.optim.Optimizer
    entries: dict[str, ShardEntry]
    rank: int
    world: int
    device: torch.device
    logger: "RankZeroLogger"

    @property
    def params(self) -> Params:
        return self.config.params


class LossModule(nn.Module):
    """The model and its objective as one module, so DDP sees the forward pass and syncs gradients."""

    def __init__(self, model: EndoflowModel, params: Params, device: torch.device) -> None:
        super().__init__()
        self.model = model
        self.loss_cfg = params.loss
        # the function, not the module, is compiled: the checkpoint's keys stay those of the plain model
        self.losses = compiled(training_step_losses, device, params.train.compile)

    def forward(self, batch: dict) -> dict[str, torch.Tensor]:
        return self.losses(self.model, batch, self.loss_cfg)


def train_loop_per_worker(config: WorkerConfig) -> None:
    """Ray Train entry point (see the module docstring)."""
    params = config.params
    context = ray.train.get_context()
    rank, world = context.get_world_rank(), context.get_world_size()
    device = ray.train.torch.get_device()
    use_cpu_threads(params.threads)  # not Ray's OMP_NUM_THREADS, which follows the worker's CPUs
    torch.manual_seed(params.seed)  # identical initial weights on every rank (DDP also broadcasts them)

    model = build_model(params, local_file(config.latent_bank) if config.latent_bank else None)
    model = to_compute_layout(model, device, params.train.precision, params.data.size)
    # a camera's intrinsics are learned only where the train shards do not know them (no unused parameters in DDP)
    model.intrinsics.learn(bool(config.learn_intrinsics), params.train.intrinsics_principal_point)
    module = ray.train.torch.prepare_model(LossModule(model, params, device), move_to_device=True)
    network = [p for name, p in model.named_parameters() if p.requires_grad and not name.startswith("intrinsics.")]
    optimizer = make_optimizer(network, params.train, list(model.intrinsics.parameters())
                               if config.learn_intrinsics else [])
    scheduler = make_scheduler(optimizer, params.train)

    state = TrainState()
    restored = restored_checkpoint(config.resume_from, rank)
    if restored is not None:
        saved, random_state = restored
        model.load_state_dict(saved.model)
        optimizer.load_state_dict(saved.optimizer)
        restore_scheduler(scheduler, saved.scheduler, optimizer)
        state = saved.state
        restore_random_state(random_state)
        if rank == 0:
            progress(f"[train] resuming after epoch {state.epoch + 1} (global step {state.global_step})")

    entries = shard_entries(config.all_train_shards + config.val_shards)
    epoch_context = EpochContext(config, module, model, optimizer, entries, rank, world, device,
                                 RankZeroLogger(config, rank))
    examples = fixed_examples(list(config.val_shards), params.train.image_examples) if rank == 0 else []
    for epoch in range(state.epoch + 1, params.train.epochs):
        seen = train_one_epoch(epoch_context, epoch, state)
        check_finite_weights(model, epoch, state)
        broadcast_buffers(model, world)
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()
        val = validate(epoch_context)
        # the history counts epochs from 1, as every output a person reads does (progress, MLflow, history.csv)
        record = {"epoch": epoch + 1, "lr": lr, "train_loss": seen["mean_loss"], **val,
                  **learned_intrinsics(model, config.learn_intrinsics, params.data.size)}
        state.history.append(record)
        if improves_on(val, state.best):
            state.best = BestEpoch(epoch, val, cpu_copy(model.state_dict()))
        state.epoch = epoch
        epoch_context.logger.epoch_end(record, state.global_step, model, examples, device)
        report_checkpoint(epoch_context, scheduler, state, seen["keys"], record)


def restored_checkpoint(resume_from: Optional[str], rank: int) -> Optional[tuple[TrainingCheckpoint, dict]]:
    """The newest of Ray's restored checkpoint and the driver's pick (the latest complete one in storage),
    with this rank's random state saved beside it. Ray's record of checkpoints can lag behind the files
    when a run is killed just after a checkpoint."""
    candidates = []
    checkpoint = ray.train.get_checkpoint()
    if checkpoint is not None:
        with checkpoint.as_directory() as folder:
            candidates.append(resume_point(folder, rank))
    if resume_from:
        candidates.append(resume_point(resume_from, rank))
    return max(candidates, key=lambda point: point[0].state.epoch, default=None)


def resume_point(location: str, rank: int) -> tuple[TrainingCheckpoint, dict]:
    """The training state of a checkpoint folder and the random state ``rank`` saved there."""
    saved = load_training_state(location)
    random_state = load_random_state(location, rank)
    if random_state is None:
        raise FileNotFoundError(f"{location}: no random state of rank {rank} (written by an older endoflow or "
                                f"with another ray.num_workers); cannot resume exactly, start a fresh run")
    return saved, random_state


def train_one_epoch(ctx: EpochContext, epoch: int, state: TrainState) -> dict[str, Any]:
    """One pass over this rank's share; returns the sample keys trained on and the mean loss."""
    cfg = ctx.params.train
    sources = [(list(urls), share) for urls, share in zip(ctx.config.train_shards, ctx.config.batch_shares)]
    batches = mixed_rank_batches(sources, ctx.rank, ctx.world, epoch, ctx.params.seed, entries=ctx.entries,
                                 loader_workers=cfg.loader_workers, pin_memory=ctx.device.type == "cuda",
                                 max_batches=cfg.steps_per_epoch)
    total_steps = steps_in_epoch(*sources[0], ctx.world, cfg, ctx.entries)
    ctx.module.train()
    keys: list[str] = []
    losses: list[float] = []
    logged = ("total", *loss_weights(ctx.config.params.loss))
    samples_per_step = cfg.batch_size * ctx.world
    # the time left counts this epoch's steps and the later epochs' at this epoch's pace (validation aside)
    epoch_progress = Progress((cfg.epochs - epoch) * total_steps * samples_per_step, "samples", clock=time.perf_counter)
    for step, batch in enumerate(batches):
        if step >= total_steps:
            break
        keys.extend(batch["key"])
        inputs = played_backwards(batch_to_device(batch, ctx.device, cfg.precision), cfg.time_reversal)
        with autocast(ctx.device, cfg.precision):
            out = ctx.module(inputs)
        reduced = mean_over_ranks(torch.stack([out[k].detach().float() for k in logged]), ctx.world)
        if not torch.isfinite(reduced).all():
            raise NonFiniteLossError(
                f"non-finite training loss {dict(zip(logged, reduced.tolist()))} at epoch {epoch}, "
                f"step {step} (global step {state.global_step}); stopped before updating the weights, "
                f"the last checkpoint (epoch {state.epoch}) is kept; lower train.lr or check the data")
        ctx.optimizer.zero_grad(set_to_none=True)
        out["total"].backward()
        if cfg.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_([p for p in ctx.model.parameters() if p.requires_grad], cfg.grad_clip)
        ctx.optimizer.step()
        state.global_step += 1
        losses.append(float(reduced[0]))
        ctx.logger.step(state.global_step, epoch, step, total_steps, dict(zip(logged, reduced.tolist())),
                        samples=(step + 1) * samples_per_step, epoch_progress=epoch_progress)
    return {"keys": keys, "mean_loss": float(np.mean(losses)) if losses else math.nan}


def played_backwards(batch: dict, share: float) -> dict:
    """``batch`` with each triplet, at chance ``share``, played backwards in time (``prev`` and ``next`` swapped).

    A camera that mostly advances teaches a pose network one forward step; played backwards, a triplet withdraws,
    so no single answer fits both and the network must read the direction from the frames. The draws come from
    torch's global generator, which checkpoints restore: a resumed run reverses the same triplets."""
    if share <= 0:
        return batch
    flip = (torch.rand(batch["cur"].shape[0]) < share).to(batch["cur"].device)[:, None, None, None]
    return {**batch, "prev": torch.where(flip, batch["next"], batch["prev"]),
            "next": torch.where(flip, batch["prev"], batch["next"])}


def improves_on(val: dict[str, float], best: Optional[BestEpoch]) -> bool:
    """Lower (or equal: later) :func:`selection_metric` wins; without validation data the latest epoch is kept."""
    if best is None:
        return True
    key = selection_metric(val)
    return val.get(key, math.inf) <= best.val.get(key, math.inf)


def selection_metric(val: dict[str, float]) -> str:
    """What picks the best epoch: val Abs Rel where the validation frames have ground-truth depth, else (unlabelled
    video) the photometric error of the held-out frames."""
    return "val_abs_rel" if "val_abs_rel" in val else "val_photometric"


def check_finite_weights(model: EndoflowModel, epoch: int, state: TrainState) -> None:
    """Refuse to checkpoint non-finite weights (the last step's update can break them after a finite loss)."""
    broken = [name for name, p in model.named_parameters() if p.requires_grad and not torch.isfinite(p).all()]
    if broken:
        raise NonFiniteLossError(
            f"non-finite weights ({broken[0]} and {len(broken) - 1} more) after the last step of epoch {epoch} "
            f"(global step {state.global_step}); the last checkpoint (epoch {state.epoch}) is kept; "
            f"lower train.lr or check the data")


def steps_in_epoch(urls: list[str], per_batch: int, world: int, cfg: TrainConfig, entries: dict[str, ShardEntry]
                   ) -> int:
    """Batches per rank this epoch: the even share of the first folder's samples at ``per_batch`` of each batch,
    capped by ``train.steps_per_epoch``."""
    share = batches_per_epoch(urls, world, per_batch, entries)
    return share if cfg.steps_per_epoch is None else min(share, cfg.steps_per_epoch)


@torch.no_grad()
def validate(ctx: EpochContext) -> dict[str, float]:
    """Over the val split, shared out over the ranks: median-scaled Abs Rel and RMSE (paper protocol) of the frames
    with ground-truth depth, and of every frame the photometric error of rebuilding it from its neighbours
    (:func:`~endoflow.losses.photometric.held_out_photometric_error`) and the share of its pixels in view whose
    depth sits at an end of its range (:func:`~endoflow.models.depth_range.at_depth_range_ends`: near 1, the
    depth has collapsed)."""
    if not ctx.config.val_shards:
        return {}
    model, params, device, world = ctx.model, ctx.params, ctx.device, ctx.world
    model.eval()
    # abs_rel, rmse, frames with depth, photometric, frames, pixels at the depth range's ends, pixels in view (on
    # the backend's device)
    sums = torch.zeros(7, dtype=torch.float64, device=device)
    batches = rank_batches(list(ctx.config.val_shards), ctx.rank, world, params.train.batch_size, 0, params.seed,
                           entries=ctx.entries, loader_workers=params.train.loader_workers,
                           pin_memory=device.type == "cuda", max_batches=params.train.val_batches)
    for index, batch in enumerate(batches):
        if params.train.val_batches is not None and index >= params.train.val_batches:
            break
        inputs = batch_to_device(batch, device, params.train.precision)
        cur, sources = inputs["cur"], [inputs["prev"], inputs["next"]]
        with autocast(device, params.train.precision):
            depth = model.predict_depth(cur)
            poses = [model.predict_pose(cur, inputs["prev"], source_is_next=False),
                     model.predict_pose(cur, inputs["next"], source_is_next=True)]
        photometric = held_out_photometric_error(cur.float(), [s.float() for s in sources], depth.float(),
                                                 [T.float() for T in poses], model.camera_K(inputs), inputs.get("valid"))
        sums[3] += photometric.double().sum()
        sums[4] += len(photometric)
        in_view = inputs["valid"].bool() if "valid" in inputs else torch.ones_like(depth, dtype=torch.bool)
        sums[5] += (at_depth_range_ends(depth.float(), params.model) & in_view).sum()
        sums[6] += in_view.sum()
        for gt, pred in zip(batch["depth"][:, 0].numpy(), depth.float().cpu().numpy()[:, 0]):
            if (gt > 0).any():
                errors = metrics.paper_depth_errors(gt, pred)
                sums[:3] += torch.tensor([errors["abs_rel"], errors["rmse"], 1.0], dtype=torch.float64, device=device)
    if world > 1:
        dist.all_reduce(sums)
    model.train()
    abs_rel, rmse, with_depth, photometric, frames, at_ends, in_view = sums.cpu().tolist()
    if frames == 0:
        return {}
    val = {"val_photometric": photometric / frames, "val_images": int(frames),
           "val_depth_at_range_ends": at_ends / max(in_view, 1.0)}
    if with_depth:
        val.update({"val_abs_rel": abs_rel / with_depth, "val_rmse": rmse / with_depth})
    return val


def report_checkpoint(ctx: EpochContext, scheduler: Any, state: TrainState, keys: list[str],
                      record: dict[str, Any]) -> None:
    """Every rank reports (Ray needs that) its random state and audit; rank 0 adds the training state."""
    with tempfile.TemporaryDirectory() as folder:
        if ctx.rank == 0:
            save_training_state(Path(folder), TrainingCheckpoint(state, ctx.model.state_dict(),
                                                                 ctx.optimizer.state_dict(), scheduler.state_dict()))
        save_random_state(Path(folder), ctx.rank)
        write_rank_audit(Path(folder), ctx.rank, state.epoch, keys, weights_digest(ctx.model),
                         ray.get_runtime_context().get_node_id())
        ray.train.report({k: v for k, v in record.items() if isinstance(v, (int, float))},
                         checkpoint=ray.train.Checkpoint.from_directory(folder),
                         checkpoint_dir_name=f"epoch-{state.epoch:04d}")


# -------------------------------------------------------------------------------------- helpers
def learned_intrinsics(model: EndoflowModel, assumed: dict[str, list[list[float]]], size: int) -> dict[str, float]:
    """``intrinsics/<dataset>/{fx,fy,cx,cy}`` (px at the stored ``size``) of each learned camera, from its assumed
    K: what the epoch's figures log."""
    figures = {}
    for dataset, K in assumed.items():
        learned = model.learned_K(dataset, torch.tensor(K, device=model.intrinsics.corrections.device),
                                  (size, size)).detach().cpu()
        for name, value in zip(("fx", "fy", "cx", "cy"), (learned[0, 0], learned[1, 1], learned[0, 2], learned[1, 2])):
            figures[f"intrinsics/{dataset}/{name}"] = float(value)
    return figures


def broadcast_buffers(model: nn.Module, world: int) -> None:
    """Give every rank rank 0's buffers (BatchNorm statistics). DDP syncs gradients, so parameters agree, but
    each rank's last forward pass updated its running statistics with its own batch; after this all ranks
    validate and checkpoint the same model."""
    if world > 1:
        for buffer in model.buffers():
            dist.broadcast(buffer, src=0)


def mean_over_ranks(values: torch.Tensor, world: int) -> torch.Tensor:
    """Mean of ``values`` over all ranks, on the CPU (a sum with any NaN stays NaN, so every rank sees it).

    The reduction runs on the values' device: NCCL (GPU) reduces CUDA tensors only, gloo CPU ones."""
    values = values.detach().double()
    if world > 1:
        dist.all_reduce(values)
    return values.cpu() / world


def cpu_copy(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in state_dict.items()}


def fixed_examples(val_urls: list[str], count: int) -> list[dict]:
    """The first sample of each of the first ``count`` val shards: the same frames every epoch."""
    examples = []
    for url in val_urls[:count]:
        sample = next(iter(triplet_dataset([url])), None)
        if sample is not None:
            examples.append(sample)
    return examples


def logged_losses(losses: dict[str, float], weights: dict[str, float]) -> dict[str, float]:
    """MLflow's names for a step's losses: ``loss/total``; each term's contribution to it as
    ``loss/weighted/<term>`` (they sum to the total); the terms before weighting as ``loss/unweighted/<term>``
    (the KL is in nats and dwarfs the total by orders of magnitude)."""
    values = {"loss/total": losses["total"]}
    for term, weight in weights.items():
        values[f"loss/weighted/{term}"] = weight * losses[term]
        if weight != 1.0:
            values[f"loss/unweighted/{term}"] = losses[term]
    return values


class RankZeroLogger:
    """Progress lines and MLflow logging; a no-op on ranks other than 0, which never load MLflow or matplotlib
    (about 2.5 s of CPU to import in every worker on 2 cores)."""

    def __init__(self, config: WorkerConfig, rank: int) -> None:
        self.active = rank == 0
        self.run = attached_run(config) if self.active else None
        self.log_every = config.params.train.log_every
        self.epochs = config.params.train.epochs
        self.precision = config.params.train.precision
        self.loss_weights = loss_weights(config.params.loss)

    def step(self, global_step: int, epoch: int, step: int, total_steps: int, losses: dict[str, float],
             samples: int, epoch_progress: Progress) -> None:
        if not self.active or (step + 1) % self.log_every and step + 1 != total_steps:
            return
        progress(f"[train] epoch {epoch + 1}/{self.epochs} step {step + 1}/{total_steps} "
                 f"loss {losses['total']:.4f} | {epoch_progress.pace(samples)} (training only)")
        self.run.log_metrics({**logged_losses(losses, self.loss_weights),
                              "samples_per_second": epoch_progress.rate(samples) or 0.0}, step=global_step)

    def epoch_end(self, record: dict[str, Any], global_step: int, model: EndoflowModel, examples: list[dict],
                  device: torch.device) -> None:
        """Progress, and MLflow: the epoch's figures and ``epoch`` (from 1) at the global step, on the per-step
        metrics' axis; the validation frames as ``val_depth/epoch_NNNN.png`` and as ``val_depth/latest.png``
        (one path in every run, which MLflow's compare page matches across runs)."""
        if not self.active:
            return
        values = {k: v for k, v in record.items() if k != "epoch" and isinstance(v, (int, float))}
        progress(f"[train] epoch {record['epoch']}/{self.epochs} done: "
                 + ", ".join(f"{k} {v:.4g}" for k, v in values.items()))
        self.run.log_metrics({**values, "epoch": record["epoch"]}, step=global_step)
        if examples:
            figure = examples_figure(model, examples, device, self.precision,
                                     f"validation frames after epoch {record['epoch']}")
            for name in (f"epoch_{record['epoch']:04d}", "latest"):
                self.run.log_figure(figure, f"val_depth/{name}.png")
            import matplotlib.pyplot as plt  # loaded with the figure, headless (endoflow.evaluation.plots)

            plt.close(figure)


def attached_run(config: WorkerConfig) -> "tracking.RunHandle":
    """The driver's MLflow run, by the id it crossed to the workers with."""
    from endoflow import tracking

    return tracking.RunHandle.attach(config.tracking_uri, config.run_id, config.unlogged_metrics)


@torch.no_grad()
def examples_figure(model: EndoflowModel, examples: list[dict], device: torch.device, precision: Precision,
                    title: str):
    was_training = model.training
    model.eval()
    rgb = images_to_device(torch.stack([e["cur"] for e in examples]), device, precision)
    with autocast(device, precision):
        depth = model.predict_depth(rgb)
    depth = depth.float().cpu().numpy()[:, 0]
    model.train(was_training)
    rows = [{"label": f"{e['meta']['sequence']} #{e['meta']['frame']}", "rgb": e["cur"].permute(1, 2, 0).numpy(),
             "gt": e["depth"][0].numpy(), "pred": d} for e, d in zip(examples, depth)]
    from endoflow.evaluation import plots  # rank 0 only (RankZeroLogger)

    return plots.depth_examples_figure(title, rows)


def progress(line: str) -> None:
    """One progress line on the process's real stdout (Ray forwards it to the driver once; Ray Train's
    patched ``print`` would also copy it into its logger, printing it twice)."""
    sys.__stdout__.write(line + "\n")
    sys.__stdout__.flush()
