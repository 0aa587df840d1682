"""Latent-bank pretraining: the SWD measure, the depth normalisation, and a tiny end-to-end run."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import webdataset as wds

from endoflow import tracking
from endoflow.config import Params
from endoflow.data.shard_format import MANIFEST, MANIFEST_SCHEMA, ShardEntry, manifest_bytes, shard_digests, shard_name
from endoflow.evaluation.swd import laplacian_pyramid, multiscale_swd
from endoflow.io import file_sha256
from endoflow.models.latent_bank import LatentBankGenerator, load_generator
from endoflow.training.pretrain import PretrainProgress, Stage, normalise_depth, pretrain_latent_bank, stage_schedule

DEPTH_UNIT_CM = 0.1


def room_depth(rng: np.random.Generator, size: int) -> np.ndarray:
    """z-depth (cm) seen from inside a random box room with one box-shaped obstacle."""
    f = size / (2 * np.tan(np.radians(30)))
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(u - size / 2) / f, (v - size / 2) / f, np.ones_like(u)], axis=-1)
    yaw, pitch = rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    rotation = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    d = rays @ rotation.T  # world directions; t along d is the z-depth since rays have z = 1
    half = rng.uniform([150, 100, 200], [400, 200, 600])
    with np.errstate(divide="ignore", invalid="ignore"):
        exits = np.where(np.abs(d) > 1e-9, (np.sign(d) * half) / d, np.inf)
    depth = exits.min(axis=-1)
    centre = rng.uniform([-100, 0, 150], [100, 80, 350])
    size3 = rng.uniform([30, 30, 30], [90, 100, 90])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (centre - size3) / d, (centre + size3) / d
    near = np.minimum(t1, t2).max(axis=-1)
    far = np.maximum(t1, t2).min(axis=-1)
    hit = (near <= far) & (near > 0)
    return np.where(hit, np.minimum(near, depth), depth).astype(np.float32)


def write_depth_shards(root: Path, counts: dict[str, int], size: int = 32, seed: int = 0) -> None:
    """SceneNet-like depth-only shards (``depth.png`` + ``meta.json``) in the shard schema, with their manifest."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    entries, rows = [], {name: [] for name in MANIFEST_SCHEMA.names}
    for split, count in counts.items():
        name = shard_name(split, 0)
        with wds.TarWriter(str(root / name)) as sink:
            for i in range(count):
                depth = room_depth(rng, size)
                ok, png = cv2.imencode(".png", np.round(depth / DEPTH_UNIT_CM).astype(np.uint16))
                assert ok
                meta = {
                    "dataset": "scenenet", "sequence": f"{split}/0/{i}", "group": "0", "split": split,
                    "frame": i, "K": np.eye(3).tolist(), "depth_unit": DEPTH_UNIT_CM, "native_size": [size, size],
                    "T_world_cam": {"prev": None, "cur": None, "next": None}, "intrinsics_known": True,
                    "ground_truth": {"depth": True, "pose": False},
                }
                key = f"scenenet-{split}-{i:04d}"
                sink.write({"__key__": key, "depth.png": png.tobytes(), "meta.json": json.dumps(meta).encode()})
                for column, value in (("shard", name), ("key", key), ("dataset", "scenenet"),
                                      ("sequence", meta["sequence"]), ("group", "0"), ("frame", i), ("split", split)):
                    rows[column].append(value)
        file_digest, samples = shard_digests(str(root / name))
        rows["sha256"].extend(digest for _, digest in samples)
        entries.append(ShardEntry(name, count, file_digest))
    (root / MANIFEST).write_bytes(manifest_bytes(rows, entries))


def test_swd_separates_sets_of_the_same_kind_from_different_kinds():
    rng = np.random.default_rng(1)
    real = torch.from_numpy(np.stack([normalise_depth(room_depth(rng, 32), 1.5) for _ in range(24)]))[:, None]
    other = torch.from_numpy(np.stack([normalise_depth(room_depth(rng, 32), 1.5) for _ in range(24)]))[:, None]
    noise = torch.randn_like(real) * 0.5
    same_kind = multiscale_swd(real, other)["mean"]
    different = multiscale_swd(real, noise)["mean"]
    assert different > 3 * same_kind


def test_laplacian_pyramid_levels_sum_back_to_the_image():
    image = torch.randn(2, 1, 64, 64)
    levels = laplacian_pyramid(image, min_resolution=16)
    assert [level.shape[-1] for level in levels] == [64, 32, 16]
    rebuilt = levels[-1]
    for band in reversed(levels[:-1]):
        rebuilt = band + torch.nn.functional.interpolate(rebuilt, size=band.shape[-2:], mode="bilinear",
                                                         align_corners=False)
    torch.testing.assert_close(rebuilt, image)


def test_normalised_depth_is_scale_free_and_in_range():
    depth = room_depth(np.random.default_rng(2), 32)
    depth[0, :4] = 0  # unknown pixels
    a, b = normalise_depth(depth, 1.5), normalise_depth(depth * 37.0, 1.5)
    np.testing.assert_allclose(a, b, atol=1e-5)
    assert a.min() >= -1 and a.max() <= 1
    assert np.all(a[0, :4] == 0)


def test_tiny_pretraining_writes_a_loadable_bank_metrics_and_plots(tmp_path, capsys):
    shards = tmp_path / "shards"
    write_depth_shards(shards, {"train": 40, "val": 16})
    params = Params()
    cfg = params.latent_bank
    cfg.resolution, cfg.start_resolution, cfg.steps_per_stage, cfg.batch_size, cfg.swd_samples = 16, 4, 4, 8, 16
    out, metrics_path, plots = tmp_path / "models/latent_bank.pt", tmp_path / "metrics/lb.json", tmp_path / "plots"

    metrics = pretrain_latent_bank(params, shards, out, metrics_path, plots, project_root=tmp_path)

    payload = torch.load(out, weights_only=True)
    assert payload["spec"]["resolution"] == 16
    generator = load_generator(str(out))
    assert isinstance(generator, LatentBankGenerator)
    assert generator(torch.randn(3, cfg.latent_dim)).shape == (3, 1, 16, 16)
    written = json.loads(metrics_path.read_text())
    # what DVC shows: two SWD figures only; the rest is in the run's metrics.json
    assert set(written) == {"latent_bank"} and set(written["latent_bank"]) == {"swd_final", "swd_ratio"}
    assert written["latent_bank"]["swd_final"] == pytest.approx(metrics["swd_final"])
    assert metrics["generator_steps"] == 3 * 4
    assert metrics["swd_untrained"] > 0 and metrics["swd_final"] > 0
    for name in ("samples_final.png", "samples_untrained.png", "losses.png"):
        image = cv2.imread(str(plots / name))
        assert image is not None and image.shape[0] > 50
    uri = tracking.tracking_uri(params, tmp_path)
    experiment = tracking.client(uri).get_experiment_by_name(params.tracking.latent_bank_experiment)
    (run,) = tracking.client(uri).search_runs([experiment.experiment_id])
    assert run.info.status == "FINISHED"
    assert run.data.metrics["swd_final"] == pytest.approx(metrics["swd_final"])
    downloaded = tracking.client(uri).download_artifacts(run.info.run_id, "metrics.json", str(tmp_path))
    logged = json.loads(Path(downloaded).read_text())
    assert logged["generator_steps"] == 3 * 4 and logged["swd_final_levels"] == metrics["swd_final_levels"]
    assert run.data.tags[tracking.LATENT_BANK_DIGEST_TAG] == file_sha256(out)
    (depth_maps,) = run.inputs.dataset_inputs
    assert depth_maps.dataset.digest == file_sha256(shards / "manifest.parquet")[:32]
    assert run.data.params["latent_bank.resolution"] == "16"
    printed = capsys.readouterr().out.splitlines()
    device = "cuda" if torch.cuda.is_available() else "cpu"  # latent_bank.device: auto
    assert printed[0] == ("[pretrain] 40 training depth maps, 16 held out for the SWD; generator steps per "
                          f"resolution: 4 px x4, 8 px x4, 16 px x4; on {device} in float32")
    assert printed[-2].startswith("[pretrain] trained 12 generator steps over 3 resolutions (4, 8, 16 px) in ")
    assert printed[-1].startswith("[pretrain] done in ") and printed[-1].endswith(f"latent bank written to {out}")


def test_steps_and_critic_steps_are_one_number_for_all_resolutions_or_one_per_resolution():
    params = Params()
    params.latent_bank.resolution, params.latent_bank.start_resolution = 16, 4
    params.latent_bank.steps_per_stage, params.latent_bank.n_critic = 7, 1
    assert stage_schedule(params) == [(4, 7, 1), (8, 7, 1), (16, 7, 1)]
    params.latent_bank.steps_per_stage, params.latent_bank.n_critic = [30, 20, 10], [3, 2, 1]
    assert stage_schedule(params) == [(4, 30, 3), (8, 20, 2), (16, 10, 1)]
    params.latent_bank.steps_per_stage = [30, 20]
    with pytest.raises(ValueError, match=r"latent_bank.steps_per_stage: expected one number or 3"):
        stage_schedule(params)
    params.latent_bank.steps_per_stage, params.latent_bank.n_critic = 5, [2, 1]
    with pytest.raises(ValueError, match=r"latent_bank.n_critic: expected one number or 3"):
        stage_schedule(params)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def losses(alpha: float = 1.0) -> dict[str, float]:
    return {"critic_loss": -1.5, "wasserstein": 2.25, "generator_loss": 0.5, "resolution": 4.0, "alpha": alpha}


def test_progress_lines_come_every_few_seconds_with_the_time_left_for_the_whole_pretraining():
    clock, lines = FakeClock(), []
    schedule = [Stage(4, 10, 1), Stage(8, 10, 1), Stage(16, 10, 2)]
    progress = PretrainProgress(schedule, interval=5.0, clock=clock, write=lines.append)

    def run_steps(count: int, seconds_each: float, alpha: float = 1.0) -> None:
        for _ in range(count):
            clock.now += seconds_each
            progress.step(losses(alpha))

    progress.start_stage(0)
    run_steps(10, 1.0)  # 1 s per step: 1/3 s per unit (a critic step counts two)
    assert len(lines) == 2  # at 5 s and 10 s, not one per step
    assert lines[0].startswith("[pretrain] 4 px (stage 1/3) step 5/10, 5/30 in all | critic -1.500, W 2.250, "
                               "generator 0.500 | 1.0 steps/s")
    # the rest of stage 1 (5 s), then stage 2 (10 steps * 3 units) and stage 3 (10 * 5 units), each at twice
    # the previous stage's time per unit until a second stage is timed: 5 + 10 * 2 + 50 / 3 * 4 = 91.7 s
    assert lines[0].endswith("~1m31s left")

    progress.start_stage(1)
    run_steps(3, 3.0, alpha=0.4)  # a unit now takes three times as long, and stage 3 is expected to triple again
    assert len(lines) == 3
    assert lines[2].startswith("[pretrain] 8 px (stage 2/3, fade-in 0.40) step 2/10, 12/30 in all")
    assert "| 0.3 steps/s |" in lines[2]
    assert progress.seconds_left(clock.now) == pytest.approx(7 * 3 * 1.0 + 10 * 5 * 3.0)

    progress.finish(losses())
    assert lines[-1] == ("[pretrain] trained 13 generator steps over 3 resolutions (4, 8, 16 px) in 0m19s "
                         "(0.7 steps/s); last losses: critic -1.500, W 2.250, generator 0.500")


def small_pretraining(tmp_path: Path, threads: int) -> tuple[str, float]:
    """(bank file SHA-256, final SWD) of a short pretraining with params ``threads``, in a fresh folder."""
    shards = tmp_path / "shards"
    if not shards.exists():
        write_depth_shards(shards, {"train": 32, "val": 16})
    params = Params()
    params.threads = threads
    cfg = params.latent_bank
    cfg.resolution, cfg.start_resolution, cfg.steps_per_stage, cfg.batch_size, cfg.swd_samples = 16, 4, 4, 8, 16
    run = tmp_path / f"run{len(list(tmp_path.glob('run*')))}"
    metrics = pretrain_latent_bank(params, shards, run / "bank.pt", run / "m.json", run / "plots", project_root=run)
    return file_sha256(run / "bank.pt"), metrics["swd_final"]


def test_the_same_seed_and_thread_count_give_the_same_bank_whatever_the_machines_thread_default(tmp_path):
    """A machine's default is its core count; 'threads' replaces it, since the count changes float sums."""
    default = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # a 1-core machine
        first = small_pretraining(tmp_path, threads=2)
        torch.set_num_threads(3)  # a 3-core machine
        second = small_pretraining(tmp_path, threads=2)
        assert torch.get_num_threads() == 2
        assert first == second  # the bank file byte for byte, and the SWD
        assert small_pretraining(tmp_path, threads=1) != first  # the count matters
    finally:
        torch.set_num_threads(default)
