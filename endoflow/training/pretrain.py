"""Generative pretraining of the latent bank on depth maps (paper section 3.1.2): WGAN-GP, progressive growing,
an exponential moving average of the generator saved (docs/method.md, "Generative latent bank").

It learns from the ``depth.png`` of the SceneNet shards' train split, as centred log-depth in [-1, 1] (scale-free:
indoor metres inform colon centimetres), and measures a sliced Wasserstein distance to the val split (or to the
last ``latent_bank.holdout_fraction`` of the train maps, left out of training, where there is no val split).
Every random draw but the gradient penalty's interpolation weights comes from a seeded CPU generator, so batches
and latents are the same on any device. Outputs (the bank file, metrics, sample grids, the MLflow run):
docs/outputs.md, "pretrain_latent_bank".
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path
from typing import Callable, NamedTuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from endoflow.config import SWD_MIN_RESOLUTION, Params
from endoflow.data.loader import list_shards, raw_samples
from endoflow.data.shard_format import decode_sample, manifest_location
from endoflow.devices import autocast, compute_dtype, resolve_device, to_compute_layout, use_cpu_threads
from endoflow.errors import DataFormatError
from endoflow.evaluation.swd import multiscale_swd
from endoflow.io import FIGURE_FOLDER, file_sha256, save_figure, save_torch, staged_directory, write_json
from endoflow.losses.gan import critic_loss, generator_loss, gradient_penalty
from endoflow.models.critic import Critic
from endoflow.models.endoflow_model import generator_spec
from endoflow.models.latent_bank import LatentBankGenerator, generator_payload
from endoflow.progress import Progress, format_duration



# ------------------------------------------------------------------------------------------------ data
def normalise_depth(depth_cm: np.ndarray, log_range: float) -> np.ndarray:
    """Centred log-depth in [-1, 1] (see the module docstring); 0 where depth is unknown (<= 0)."""
    known = depth_cm > 0
    out = np.zeros_like(depth_cm, dtype=np.float32)
    if known.any():
        log_depth = np.log(depth_cm[known])
        out[known] = np.clip((log_depth - log_depth.mean()) / log_range, -1.0, 1.0)
    return out


def load_depth_maps(urls: list[str], resolution: int, log_range: float) -> torch.Tensor:
    """All depth maps of ``urls``, normalised, area-resized to ``[N, 1, resolution, resolution]``."""
    maps = []
    for sample in raw_samples(urls):
        normalised = normalise_depth(decode_sample(sample)["depth"][0].numpy(), log_range)
        maps.append(cv2.resize(normalised, (resolution, resolution), interpolation=cv2.INTER_AREA))
    if not maps:
        raise DataFormatError(urls[0] if urls else "?", "no depth samples in these shards")
    return torch.from_numpy(np.stack(maps))[:, None]


def train_and_heldout(shards_dir: Path, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    cfg = params.latent_bank
    train_urls = list_shards(str(shards_dir), "train")
    if not train_urls:
        raise DataFormatError(shards_dir, "no train-*.tar shards (run the preprocess stage for scenenet)")
    train = load_depth_maps(train_urls, cfg.resolution, cfg.depth_log_range)
    val_urls = list_shards(str(shards_dir), "val")
    if val_urls:
        return train, load_depth_maps(val_urls, cfg.resolution, cfg.depth_log_range)
    cut = len(train) - max(1, int(round(cfg.holdout_fraction * len(train))))
    if cut < 1:
        raise DataFormatError(shards_dir, f"too few depth maps ({len(train)}) to hold some out")
    return train[:cut], train[cut:]


def at_resolution(maps: torch.Tensor, resolution: int, alpha: float) -> torch.Tensor:
    """Maps at ``resolution``, blended with their upsampled half-resolution version during a fade-in."""
    if maps.shape[-1] != resolution:
        maps = F.interpolate(maps, size=(resolution, resolution), mode="area")
    if alpha < 1.0:
        coarse = F.interpolate(F.avg_pool2d(maps, 2), scale_factor=2, mode="nearest")
        maps = alpha * maps + (1 - alpha) * coarse
    return maps


# -------------------------------------------------------------------------------------------- training
class EMA:
    """Exponential moving average of a model's parameters and buffers, warmed up over the first steps."""

    def __init__(self, model: torch.nn.Module, decay: float) -> None:
        self.model = copy.deepcopy(model).requires_grad_(False)
        self.decay = decay
        self.updates = 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        # Early on the average would be mostly the random initialisation; ramp the decay up.
        decay = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for avg, new in zip(self.model.state_dict().values(), model.state_dict().values()):
            avg.lerp_(new, 1 - decay)


class Stage(NamedTuple):
    """One progressive stage: its resolution, generator steps and critic steps per generator step."""

    resolution: int
    steps: int
    n_critic: int


def per_resolution(key: str, value: int | list[int], resolutions: list[int]) -> list[int]:
    """``value`` for each resolution: one number for all, or a list with one entry per resolution."""
    if isinstance(value, int):
        return [value] * len(resolutions)
    if len(value) != len(resolutions):
        raise ValueError(f"latent_bank.{key}: expected one number or {len(resolutions)} (one per "
                         f"resolution {resolutions}), got {value}")
    return list(value)


def stage_schedule(params: Params) -> list[Stage]:
    """The progressive stages, coarsest first."""
    cfg = params.latent_bank
    resolutions = generator_spec(params).resolutions
    steps = per_resolution("steps_per_stage", cfg.steps_per_stage, resolutions)
    critic_steps = per_resolution("n_critic", cfg.n_critic, resolutions)
    return [Stage(*stage) for stage in zip(resolutions, steps, critic_steps)]


@torch.no_grad()
def generate(
    generator: LatentBankGenerator, count: int, latent_dim: int, seed: int, device: torch.device, batch: int = 64
) -> torch.Tensor:
    """``count`` maps at the full resolution from latents drawn with ``seed`` (on the CPU, so the same latents
    on every device), computed in float32 on ``device``: the SWD measures the weights as the bank file keeps them."""
    rng = torch.Generator().manual_seed(seed)
    z = torch.randn(count, latent_dim, generator=rng).to(device)
    return torch.cat([generator(z[i : i + batch]) for i in range(0, count, batch)])


def swd_against(heldout: torch.Tensor, fake: torch.Tensor, seed: int) -> dict:
    n = min(len(heldout), len(fake))
    return multiscale_swd(heldout[:n], fake[:n], min_resolution=SWD_MIN_RESOLUTION, seed=seed)


def train_gan(
    params: Params,
    train: torch.Tensor,
    device: torch.device,
    log: Callable[[dict[str, float], int], None],
) -> tuple[EMA, list[dict[str, float]]]:
    """Progressive WGAN-GP training on ``device`` (``train`` is moved there) in ``latent_bank.precision``;
    returns the generator's moving average and the loss history."""
    cfg = params.latent_bank
    spec = generator_spec(params)
    # Built on the CPU from the global seed, then moved: the same initial weights on every device.
    generator, critic = LatentBankGenerator(spec), Critic(spec)
    generator = to_compute_layout(generator, device, cfg.precision, spec.resolution)
    critic = to_compute_layout(critic, device, cfg.precision, spec.resolution)
    ema = EMA(generator, cfg.ema_decay)
    opt_g = torch.optim.Adam(generator.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
    opt_c = torch.optim.Adam(critic.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
    rng = torch.Generator().manual_seed(params.seed)  # CPU draws, moved to the device (module docstring)
    train = train.to(device)

    def latents() -> torch.Tensor:
        return torch.randn(cfg.batch_size, spec.latent_dim, generator=rng).to(device)

    history: list[dict[str, float]] = []
    schedule = stage_schedule(params)
    progress = PretrainProgress(schedule)
    step = 0
    for stage, (resolution, steps, n_critic) in enumerate(schedule):
        progress.start_stage(stage)
        reals = at_resolution(train, resolution, 1.0)
        fade_steps = max(1, int(cfg.fade_fraction * steps)) if stage > 0 else 0
        for i in range(steps):
            alpha = min(1.0, i / fade_steps) if fade_steps else 1.0

            def score(x: torch.Tensor) -> torch.Tensor:
                # Only the forward pass is autocast: the penalty's gradient and every loss are float32 tensors.
                with autocast(device, cfg.precision):
                    return critic(x, resolution, alpha).float()

            def synthesize(z: torch.Tensor) -> torch.Tensor:
                with autocast(device, cfg.precision):
                    return generator(z, resolution, alpha).float()

            for _ in range(n_critic):
                index = torch.randint(len(reals), (cfg.batch_size,), generator=rng).to(device)
                real = at_resolution(reals[index], resolution, alpha)
                flip = (torch.rand(cfg.batch_size, generator=rng) < 0.5).to(device)
                real = torch.where(flip[:, None, None, None], real.flip(-1), real)
                with torch.no_grad():
                    fake = synthesize(latents())
                real_scores, fake_scores = score(real), score(fake)
                loss_c = (
                    critic_loss(real_scores, fake_scores)
                    + gradient_penalty(score, real, fake, cfg.gp_gamma)
                    + cfg.drift_weight * real_scores.square().mean()
                )
                opt_c.zero_grad(set_to_none=True)
                loss_c.backward()
                opt_c.step()
            fake = synthesize(latents())
            loss_g = generator_loss(score(fake))
            opt_g.zero_grad(set_to_none=True)
            loss_g.backward()
            opt_g.step()
            ema.update(generator)
            record = {
                "critic_loss": loss_c.item(),
                "wasserstein": (real_scores.mean() - fake_scores.mean()).item(),
                "generator_loss": loss_g.item(),
                "resolution": float(resolution),
                "alpha": alpha,
            }
            history.append(record)
            progress.step(record)
            if step % 25 == 0:
                log(record, step)
            step += 1
    progress.finish(history[-1])
    return ema, history


# ------------------------------------------------------------------------------------------- progress
PROGRESS_INTERVAL_S = 5.0
# A critic step runs the gradient penalty's double backward: about two generator steps' time (CPU, measured at
# the default sizes).
CRITIC_STEP_COST = 2.0
# Until a second stage has been timed, assume a unit's time doubles with each resolution (CPU, default sizes).
ASSUMED_STAGE_GROWTH = 2.0


def report_line(line: str) -> None:
    """One progress line on stdout, flushed (the stage's output is often a pipe, block-buffered)."""
    print(line, flush=True)


def step_work(stage: Stage) -> float:
    """The cost of one of the stage's generator steps with its critic steps, in units of a bare generator step."""
    return 1 + CRITIC_STEP_COST * stage.n_critic


class PretrainProgress:
    """Progress lines at most every ``interval`` seconds, and a summary at the end (through ``write``).

    Time left covers the whole pretraining: the rest of the current stage at its measured pace, and every
    later stage at that pace times its work (:func:`step_work`) and the growth of a unit's time from one
    resolution to the next (measured between the current stage and the previous one, at least 1; assumed
    ``ASSUMED_STAGE_GROWTH`` during the first stage).
    """

    def __init__(
        self,
        schedule: list[Stage],
        interval: float = PROGRESS_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        write: Callable[[str], None] = report_line,
    ) -> None:
        self.schedule, self.interval, self.clock, self.write = schedule, interval, clock, write
        self.total = sum(stage.steps for stage in schedule)
        self.overall = Progress(self.total, "steps", clock=clock)
        self.done = self.stage_done = 0
        self.stage = 0
        # the pace is the current stage's (a higher resolution is slower)
        self.stage_progress = Progress(schedule[0].steps, "steps", interval, clock)
        self.unit_seconds: list[float] = []  # measured seconds per work unit of each finished stage

    def start_stage(self, stage: int) -> None:
        if stage > 0:
            self.unit_seconds.append(self._unit_seconds(self.clock()))
        self.stage, self.stage_done = stage, 0
        self.stage_progress = Progress(self.schedule[stage].steps, "steps", self.interval, self.clock)

    def step(self, record: dict[str, float]) -> None:
        """After each generator step: a line when ``interval`` has passed since the last one (or a stage ends)."""
        self.done += 1
        self.stage_done += 1
        if not self.stage_progress.due(self.stage_done):
            return
        stage = self.schedule[self.stage]
        fade = f", fade-in {record['alpha']:.2f}" if record["alpha"] < 1 else ""
        self.write(
            f"[pretrain] {stage.resolution} px (stage {self.stage + 1}/{len(self.schedule)}{fade}) "
            f"step {self.stage_done}/{stage.steps}, {self.done}/{self.total} in all | "
            f"critic {record['critic_loss']:.3f}, W {record['wasserstein']:.3f}, "
            f"generator {record['generator_loss']:.3f} | "
            f"{self.stage_progress.pace(self.stage_done, self.seconds_left(self.clock()))}"
        )

    def seconds_left(self, now: float) -> float:
        pace = self._unit_seconds(now)
        growth = max(1.0, pace / self.unit_seconds[-1]) if self.unit_seconds else ASSUMED_STAGE_GROWTH
        current = self.schedule[self.stage]
        left = (current.steps - self.stage_done) * step_work(current) * pace
        for distance, later in enumerate(self.schedule[self.stage + 1 :], start=1):
            left += later.steps * step_work(later) * pace * growth**distance
        return left

    def finish(self, record: dict[str, float]) -> None:
        """The summary line: steps, time, pace and the last losses."""
        self.write(
            f"[pretrain] trained {self.done} generator steps over {len(self.schedule)} resolutions "
            f"({', '.join(str(stage.resolution) for stage in self.schedule)} px) in "
            f"{format_duration(self.overall.elapsed())} ({self.overall.rate(self.done) or 0.0:.1f} steps/s); "
            f"last losses: critic {record['critic_loss']:.3f}, "
            f"W {record['wasserstein']:.3f}, generator {record['generator_loss']:.3f}"
        )

    def _unit_seconds(self, now: float) -> float:
        """Seconds per work unit in the current stage so far."""
        return (now - self.stage_progress.started) / (self.stage_done * step_work(self.schedule[self.stage]))


# -------------------------------------------------------------------------------------------- outputs
def save_sample_grid(fake: torch.Tensor, real: torch.Tensor, path: Path, title: str) -> None:
    """PNG: generated maps (left block) beside real held-out maps (right block), same colour scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(16, len(fake), len(real))
    cols = int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, 2 * cols, figsize=(2 * cols * 1.3, rows * 1.3 + 0.5), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for block, maps in enumerate((fake, real)):
        for i in range(n):
            ax = axes[i // cols, block * cols + i % cols]
            ax.imshow(maps[i, 0].cpu().numpy(), cmap="magma_r", vmin=-1, vmax=1)
    axes[0, 0].set_title("generated", loc="left", fontsize=9)
    axes[0, cols].set_title("real (held out)", loc="left", fontsize=9)
    fig.suptitle(title, fontsize=9)
    save_figure(path, fig, dpi=80)


def save_loss_curves(history: list[dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3))
    steps = np.arange(len(history))
    for key in ("wasserstein", "generator_loss"):
        ax.plot(steps, [h[key] for h in history], label=key, linewidth=0.8)
    for i in range(1, len(history)):
        if history[i]["resolution"] != history[i - 1]["resolution"]:
            ax.axvline(i, color="grey", linewidth=0.5)
    ax.set_xlabel("generator step (grey lines: new resolution)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(path, fig, dpi=80)


# ------------------------------------------------------------------------------------------ entry point
def pretrain_latent_bank(
    params: Params,
    shards_dir: str | Path,
    out_path: str | Path,
    metrics_path: str | Path,
    plots_dir: str | Path,
    project_root: str | Path | None = None,
) -> dict:
    """Pretrain the latent bank on the depth maps in ``shards_dir`` and write all outputs.

    ``project_root`` (default: the working directory) locates the MLflow store (see
    :mod:`endoflow.tracking`). Returns the metrics dict written to ``metrics_path``.
    """
    from endoflow import tracking

    started = time.time()
    use_cpu_threads(params.threads)
    torch.manual_seed(params.seed)
    cfg = params.latent_bank
    shards_dir, out_path, metrics_path, plots_dir = map(Path, (shards_dir, out_path, metrics_path, plots_dir))
    project_root = Path(project_root) if project_root is not None else Path.cwd()
    device = resolve_device(cfg.device, "latent_bank.device")
    train, heldout = (maps.to(device) for maps in train_and_heldout(shards_dir, params))
    swd_count = min(cfg.swd_samples, len(heldout))
    heldout = heldout[:swd_count]
    stages = ", ".join(f"{stage.resolution} px x{stage.steps}" for stage in stage_schedule(params))
    dtype = str(compute_dtype(device, cfg.precision)).removeprefix("torch.")
    report_line(f"[pretrain] {len(train)} training depth maps, {swd_count} held out for the SWD; "
                f"generator steps per resolution: {stages}; on {device} in {dtype}")

    with tracking.run(params, project_root, params.tracking.latent_bank_experiment,
                      tracking.run_name_for("latent-bank", [f"seed{params.seed}"])) as run:
        run.log_shards_input(manifest_location(str(shards_dir)), shards_dir.name, "training")
        spec = generator_spec(params)
        untrained = LatentBankGenerator(spec).to(device)
        fake_untrained = generate(untrained, swd_count, spec.latent_dim, params.seed + 1, device)
        swd_untrained = swd_against(heldout, fake_untrained, params.seed)
        swd_reference = swd_against(heldout, train[:swd_count], params.seed)
        report_line(f"[pretrain] SWD to the held-out maps: untrained generator {swd_untrained['mean']:.1f}, "
                    f"real training maps {swd_reference['mean']:.1f} (the floor)")

        ema, history = train_gan(params, train, device, run.log_metrics)
        fake_final = generate(ema.model, swd_count, spec.latent_dim, params.seed + 1, device)
        swd_final = swd_against(heldout, fake_final, params.seed)

        payload = generator_payload(
            ema.model,
            {"normalisation": {"kind": "centred_log_depth", "depth_log_range": cfg.depth_log_range}},
        )
        save_torch(out_path, payload)
        run.set_tags({tracking.LATENT_BANK_DIGEST_TAG: file_sha256(out_path)})

        with staged_directory(plots_dir, FIGURE_FOLDER) as folder:
            save_sample_grid(fake_final, heldout, folder / "samples_final.png",
                             f"EMA generator, SWD {swd_final['mean']:.1f}")
            save_sample_grid(fake_untrained, heldout, folder / "samples_untrained.png",
                             f"untrained generator, SWD {swd_untrained['mean']:.1f}")
            save_loss_curves(history, folder / "losses.png")

        metrics = {
            "swd_untrained": swd_untrained["mean"],
            "swd_final": swd_final["mean"],
            "swd_real_reference": swd_reference["mean"],
            "swd_untrained_levels": swd_untrained["levels"],
            "swd_final_levels": swd_final["levels"],
            "swd_ratio": swd_final["mean"] / swd_untrained["mean"],
            "generator_steps": len(history),
            "train_maps": len(train),
            "heldout_maps": swd_count,
            "seconds": time.time() - started,
        }
        write_json(metrics_path, dvc_metrics(metrics))
        report_line(summary_line(metrics, out_path))
        # the headline as metrics (columns of the runs table); the one-off figures in metrics.json, not charts
        headline = dvc_metrics(metrics)["latent_bank"]
        run.log_metrics(headline, step=len(history))
        run.show_in_runs_table(headline)
        run.log_dict(metrics, "metrics.json")
        run.log_artifact(plots_dir, "plots")
        run.log_artifact(out_path)
    return metrics


def dvc_metrics(metrics: dict) -> dict[str, dict[str, float]]:
    """What ``latent_bank.metrics`` holds for DVC, under ``latent_bank``: the trained generator's SWD and its
    ratio to the untrained one's (both unitless); the other figures stay in the run's ``metrics.json`` in MLflow,
    so that ``dvc metrics show`` stays narrow."""
    return {"latent_bank": {key: float(metrics[key]) for key in ("swd_final", "swd_ratio")}}


def summary_line(metrics: dict, out_path: Path) -> str:
    """The closing line of a pretraining run: SWD before and after, its floor, time and the bank's file."""
    return (
        f"[pretrain] done in {format_duration(metrics['seconds'])}: SWD {metrics['swd_untrained']:.1f} untrained "
        f"-> {metrics['swd_final']:.1f} trained (ratio {metrics['swd_ratio']:.2f}; real-vs-real floor "
        f"{metrics['swd_real_reference']:.1f}); latent bank written to {out_path}"
    )
