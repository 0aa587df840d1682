"""Evaluation end to end on tiny shards: an oracle scores zero, baselines do not, outputs follow the formats.

The shards hold "oracle-readable" frames: the red channel encodes the GT depth of each pixel and the green
channel the frame's index, so :class:`OracleModel` can answer with the exact GT depth and pose. Everything
the evaluation does between shards and metrics (frame order, edge frames, relative-pose direction, the
challenge files) must then give zero error.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from endoflow import tracking
from endoflow.config import Params, EvalSetConfig
from endoflow.data.base import Sequence
from endoflow.data.sequences import frames_in_order, sequence_frames
from endoflow.data.shards import write_dataset_shards
from endoflow.io import file_sha256
from endoflow.evaluation import metrics
from endoflow.evaluation.results import PROTOCOLS
from endoflow.evaluation.evaluate import (
    SequenceEvaluator,
    SequenceResult,
    batches_within_sequences,
    evaluate_test_set,
    longest_posed_run,
    pose_sequence_scores,
    score_sequences,
    eval_set_shards,
)
from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
from tests.test_path_smoothing import pose as rigid_pose

SIZE = 64  # the smallest size the depth network accepts (its deepest features are 2x2)
FRAMES = 7
DEPTH_STEP_CM = 0.05  # depth = 1 cm + red * step: exactly representable in the shards' 0.001 cm unit
K = np.array([[40.0, 0.0, 31.5], [0.0, 40.0, 31.5], [0.0, 0.0, 1.0]])
SEQUENCES = {"S1": ("SyntheticColon_I", "train"), "S2": ("SyntheticColon_I", "train"),
             "S4": ("SyntheticColon_I", "val"), "S9": ("SyntheticColon_I", "val"),
             "S5": ("SyntheticColon_I", "test"), "B5": ("SyntheticColon_II", "test"),
             "O1": ("SyntheticColon_III", "test")}


def trajectory(index: int) -> np.ndarray:
    """GT ``T_world_cam`` of frame ``index``: forward along z while yawing and drifting, faster and faster."""
    angle = 0.05 * index + 0.01 * index**2
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    pose[:3, 3] = (0.3 * index, -0.1 * index, 1.0 + 0.8 * index + 0.1 * index**2)
    return pose


def oracle_rgb(index: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, index])
    rgb = rng.integers(0, 256, size=(SIZE, SIZE, 3), dtype=np.uint8)
    rgb[..., 1] = 10 * index  # the frame index, read back by the oracle
    return rgb


def oracle_depth(index: int, seed: int) -> np.ndarray:
    return (1.0 + oracle_rgb(index, seed)[..., 0].astype(np.float32) * DEPTH_STEP_CM).astype(np.float32)


@dataclass
class OracleSource:
    """Picklable source of the sequences above (frames 0..FRAMES-1, poses of :func:`trajectory`)."""

    def __call__(self) -> list[Sequence]:
        return [self.sequence(i, name, group, split) for i, (name, (group, split)) in enumerate(SEQUENCES.items())]

    @staticmethod
    def sequence(seed: int, name: str, group: str, split: str) -> Sequence:
        return Sequence(dataset="simcol", name=name, split=split, K=K, image_size=(SIZE, SIZE),
                        frame_ids=list(range(FRAMES)), poses=np.stack([trajectory(i) for i in range(FRAMES)]),
                        load_rgb=lambda i: oracle_rgb(i, seed), load_depth=lambda i: oracle_depth(i, seed),
                        group=group)


class OracleModel(torch.nn.Module):
    """Reads GT depth and frame index back out of the oracle frames."""

    def predict_depth(self, rgb: torch.Tensor) -> torch.Tensor:
        red = torch.round(rgb[:, :1] * 255)
        return 1.0 + red * DEPTH_STEP_CM

    def predict_pose(self, target: torch.Tensor, source: torch.Tensor, source_is_next: bool = True) -> torch.Tensor:
        assert not source_is_next, "the evaluation asks for T_earlier_later with the earlier frame as source"
        poses = []
        for t, s in zip(target, source):
            t_index, s_index = (int(round(float(x[1, 0, 0]) * 255 / 10)) for x in (t, s))
            poses.append(np.linalg.inv(trajectory(s_index)) @ trajectory(t_index))
        return torch.from_numpy(np.stack(poses))


def shard_params(out_root: Path) -> Params:
    params = Params()
    params.data.size = SIZE
    params.preprocess = params.preprocess.replace(workers=1, samples_per_shard=4, shard_multiple=2)
    params.eval.shards = str(out_root)
    params.eval.batch_size = 4
    return params


@pytest.fixture(scope="session")
def oracle_shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``<root>/simcol/`` shards of the oracle sequences (train, val and test splits)."""
    root = tmp_path_factory.mktemp("oracle_shards")
    write_dataset_shards(OracleSource(), "simcol", shard_params(root), root / "simcol")
    return root


def oracle_baselines() -> TrainingBaselines:
    mean_pose = np.eye(4)
    mean_pose[:3, 3] = (0.3, -0.1, 0.8)
    return TrainingBaselines(mean_depth_cm=7.0, mean_depth_map=np.full((SIZE, SIZE), 7.0, np.float32),
                             mean_relative_pose=mean_pose)


def run_oracle(root: Path, test_set: EvalSetConfig, out: Path) -> SequenceEvaluator:
    evaluator = SequenceEvaluator(OracleModel(), oracle_baselines(), out, torch.device("cpu"), "float32",
                                  max_examples=2)
    frames = sequence_frames(eval_set_shards(str(root), test_set), lambda meta: meta["group"] in test_set.groups)
    for batch in batches_within_sequences(frames, size=3):
        evaluator.process(batch)
    return evaluator


def test_oracle_scores_zero_in_every_protocol_and_baselines_do_not(oracle_shards: Path, tmp_path: Path):
    test_set = EvalSetConfig(dataset="simcol", groups=["SyntheticColon_I", "SyntheticColon_II"])
    evaluator = run_oracle(oracle_shards, test_set, tmp_path)
    assert [s.name for s in evaluator.sequences] == ["S5", "B5"]
    # every frame, including the first (a prev) and the last (a next), in temporal order
    assert all(s.frames == list(range(FRAMES)) for s in evaluator.sequences)
    summary, per_frame, per_sequence, trajectories = score_sequences(evaluator)

    model = summary["depth_paper"]["model"]
    assert model["abs_rel"] == pytest.approx(0.0, abs=1e-4) and model["a1"] == 1.0
    assert model["ratio"] == pytest.approx(1.0, abs=1e-4)  # metric depth needs no scaling
    # the challenge protocol scores float16 predictions of depth / 20, as its files hold them
    assert summary["depth_simcol"]["model"]["l1"] == pytest.approx(0.0, abs=5e-3)
    assert summary["depth_simcol"]["model"]["rel"] == pytest.approx(0.0, abs=0.05)
    for key in metrics.SIMCOL_POSE_KEYS:
        assert summary["pose_simcol"]["model"][key] == pytest.approx(0.0, abs=1e-4), key
    assert summary["pose_endoslam"]["model"]["ate"] == pytest.approx(0.0, abs=1e-4)
    np.testing.assert_allclose(trajectories["S5"]["model"], trajectories["S5"]["gt"], atol=1e-4)
    # the oracle follows every change of the motion, at the depth's scale; constant velocity follows none
    for key in ("step_corr", "forward_corr", "rotation_corr", "step_spread"):
        assert summary["pose_motion"]["model"][key] == pytest.approx(1.0, abs=1e-3), key
        assert summary["pose_motion"]["constant_velocity"][key] == 0.0, key
    assert summary["scale"]["model"] == pytest.approx({"path_over_depth": 1.0, "depth_drift": 1.0}, abs=1e-3)

    assert summary["depth_paper"]["constant_depth"]["abs_rel"] > 0.1
    assert summary["depth_paper"]["mean_depth_map"]["abs_rel"] > 0.1
    assert summary["pose_simcol"]["constant_velocity"]["rot"] > 1.0  # the GT turns, the baseline does not
    assert len(per_frame) == 2 * FRAMES and list(per_sequence["sequence"]) == ["S5", "B5"]
    # GT depth exists for the shards' target frames only (not the edge frames)
    assert per_frame["abs_rel_model"].notna().sum() == 2 * (FRAMES - 2)


def test_challenge_files_have_the_official_names_sizes_and_values(oracle_shards: Path, tmp_path: Path):
    test_set = EvalSetConfig(dataset="simcol", groups=["SyntheticColon_III"])
    run_oracle(oracle_shards, test_set, tmp_path)
    folder = tmp_path / "SyntheticColon_III_Test" / "Frames_O1_OP"
    depth_files = sorted((folder / "depth").iterdir())
    pose_files = sorted((folder / "pose").iterdir())
    assert [p.name for p in depth_files] == [f"FrameBuffer_{i:04d}.npy" for i in range(FRAMES)]
    assert [p.name for p in pose_files] == [f"FrameBuffer_{i:04d}_to_FrameBuffer_{i + 1:04d}.txt"
                                            for i in range(FRAMES - 1)]
    depth = np.load(depth_files[3])
    assert depth.dtype == np.float16 and depth.shape == (SIZE, SIZE)
    np.testing.assert_allclose(depth.astype(np.float64) * 20, oracle_depth(3, seed=6), rtol=2e-3)
    relative = np.array(pose_files[2].read_text().split(), dtype=np.float64).reshape(4, 4)
    np.testing.assert_allclose(relative, np.linalg.inv(trajectory(2)) @ trajectory(3), atol=1e-6)


def test_missing_poses_leave_the_longest_posed_run():
    pose = np.eye(4)
    assert longest_posed_run([pose, None, pose, pose, pose, None, pose, pose]) == (2, 5)
    assert longest_posed_run([pose, None, pose]) is None


def test_the_refined_path_is_scored_with_its_orientations_smoothed_as_reconstruct_writes_them():
    from endoflow.geometry.path_smoothing import smooth_path_orientations

    rng = np.random.default_rng(0)
    steps = [rigid_pose((0.001, -0.002, 0.0005), (0.0, 0.01, 0.1 + 0.01 * np.sin(i))) for i in range(29)]
    truth = metrics.chain_relative_poses(np.eye(4), np.stack(steps))  # a steady turn
    aligned = np.stack([T @ rigid_pose(rng.normal(0, 0.001, 3), (0, 0, 0)) for T in truth])
    seq = SequenceResult("S1", "SyntheticColon_I", frames=list(range(31)), poses=[None, *truth],
                         predicted_relative=[np.eye(4)] + [metrics.relative_poses(truth)[0]] * 29,
                         refined=[np.eye(4), *aligned])

    def refined_figures(smoothing: float) -> dict[str, float]:
        rows, _ = pose_sequence_scores(seq, oracle_baselines(), smoothing)
        return {row["metric"]: row["value"] for row in rows
                if row["method"] == "refined" and row["protocol"] == "pose_simcol" and row["frame"] is None}

    # the first frame has no GT pose and is not scored, but is tracked: the path is smoothed whole, then cut
    expected = metrics.simcol_pose_sequence(
        truth, metrics.relative_poses(smooth_path_orientations(np.stack([np.eye(4), *aligned]), 2.0)[1:]))
    unsmoothed = metrics.simcol_pose_sequence(truth, metrics.relative_poses(aligned))
    smoothed, as_aligned = refined_figures(2.0), refined_figures(0.0)
    assert smoothed["rot"] == pytest.approx(expected["rot"]) and smoothed["rte"] == pytest.approx(expected["rte"])
    assert as_aligned["rot"] == pytest.approx(unsmoothed["rot"])
    assert smoothed["rot"] < 0.3 * as_aligned["rot"]
    assert max(smoothed["rte"], as_aligned["rte"]) < 0.002 * 0.1  # 0.2 % of a step: the positions are as aligned


def test_the_refined_paths_scale_is_compared_with_the_depth_as_the_tracker_rescaled_it():
    """With ``refine.depth_scale`` the tracker multiplies each frame's depth by a factor, and the refined path has
    the depth's scale so rescaled: its scale figures divide each frame's ratio of GT over predicted depth by that
    factor; the network's keep the depth as predicted. The truth advances 0.1 a frame, both paths 0.05, the ground
    truth is twice the predicted depth, and the tracker doubled the depth from the fifth frame on."""
    truth = [rigid_pose((0, 0, 0), (0, 0, 0.1 * i)) for i in range(9)]
    half = rigid_pose((0, 0, 0), (0, 0, 0.05))
    seq = SequenceResult("S1", "SyntheticColon_I", frames=list(range(9)), poses=truth,
                         predicted_relative=[half] * 8, refined=[rigid_pose((0, 0, 0), (0, 0, 0.05 * i))
                                                                 for i in range(9)],
                         depth_ratios=[2.0] * 9, depth_scales=[1.0] * 4 + [2.0] * 5)

    def scale_figures(method: str) -> dict[str, float]:
        rows, _ = pose_sequence_scores(seq, oracle_baselines())
        return {row["metric"]: row["value"] for row in rows if row["method"] == method and row["protocol"] == "scale"}

    assert scale_figures("model") == pytest.approx({"path_over_depth": 1.0, "depth_drift": 1.0})
    # rescaled ratios 2, 2, 2, 2, 1, 1, 1, 1, 1: median 1, the last quarter's half the first's
    assert scale_figures("refined") == pytest.approx({"path_over_depth": 2.0, "depth_drift": 0.5})
    seq.depth_scales = [1.0] * 9  # the setting off: the refined path's figures are the network's
    assert scale_figures("refined") == pytest.approx(scale_figures("model"))


def test_the_refined_path_is_smoothed_apart_on_either_side_of_missing_frames():
    """After missing frames the tracker starts anew from the identity: the smoothing never reaches across."""
    from endoflow.evaluation.evaluate import refined_path
    from endoflow.geometry.path_smoothing import smooth_path_orientations

    rng = np.random.default_rng(1)
    stretch = [rigid_pose(rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3)) for _ in range(20)]
    restarted = [rigid_pose(rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3)) for _ in range(12)]
    seq = SequenceResult("S1", "SyntheticColon_I", frames=[*range(20), *range(25, 37)], gaps={20},
                         refined=[*stretch, *restarted])
    expected = np.concatenate([smooth_path_orientations(np.stack(stretch), 2.0),
                               smooth_path_orientations(np.stack(restarted), 2.0)])
    np.testing.assert_array_equal(refined_path(seq, 2.0), expected)
    assert not np.allclose(refined_path(seq, 2.0), smooth_path_orientations(np.stack(seq.refined), 2.0))
    np.testing.assert_array_equal(refined_path(seq, 0.0), np.stack(seq.refined))


def test_unknown_test_set_groups_fail_naming_what_exists(oracle_shards: Path):
    with pytest.raises(ValueError, match="found groups .*SyntheticColon_III"):
        eval_set_shards(str(oracle_shards), EvalSetConfig(dataset="simcol", groups=["Colon"]))


def write_untrained_model(path: Path, params: Params, run_id: str | None) -> None:
    from endoflow.models.endoflow_model import build_model

    torch.manual_seed(0)
    model = build_model(params, latent_bank_path=None)
    save_model_file(path, ModelRecord(params=params, state=model.state_dict(), epoch=0, val={"val_abs_rel": 1.0},
                                      mlflow_run_id=run_id, baselines=oracle_baselines()))


def test_evaluate_stage_writes_metrics_plots_predictions_and_logs_to_the_training_run(
        oracle_shards: Path, tmp_path: Path):
    from endoflow.evaluation.evaluate import log_evaluation

    params = shard_params(oracle_shards)
    params.model = params.model.replace(latent_bank=False)
    uri = tracking.tracking_uri(params, tmp_path)
    manifest = oracle_shards / "simcol" / "manifest.parquet"
    with tracking.run(params, tmp_path, "endoflow", "train") as run:
        run.log_shards_input(str(manifest), "simcol", "training")  # trained on the same folder
    run_id = run.run_id
    write_untrained_model(tmp_path / "endoflow.pt", params, run_id)
    urls = eval_set_shards(str(oracle_shards), params.eval.test_sets["simcol_3"])
    result = evaluate_test_set(params, "simcol_3", urls, tmp_path / "endoflow.pt", tmp_path / "m.json",
                               tmp_path / "plots", tmp_path / "predictions")
    log_evaluation(params, tmp_path, result, tmp_path / "plots")

    written = json.loads((tmp_path / "predictions" / "evaluation.json").read_text())
    assert written == json.loads(json.dumps(result))
    assert written["sequences"] == 1 and written["frames"] == FRAMES and written["mlflow_run_id"] == run_id
    assert set(written["depth_paper"]) == {"model", "constant_depth", "mean_depth_map"}
    assert set(written["pose_simcol"]) == {"model", "refined", "constant_velocity"}  # refine.enabled
    assert set(written["depth_simcol"]["model"]) == {"l1", "rel", "rmse"}
    # what DVC reads: the headline, under a key of the test set's own, each name with its unit
    assert json.loads((tmp_path / "m.json").read_text()) == {"test_simcol_3": {
        "abs_rel": written["depth_paper"]["model"]["abs_rel"], "rte_cm": written["pose_simcol"]["model"]["rte"],
        "rot_deg": written["pose_simcol"]["model"]["rot"]}}
    # pictures in the plots folder; the tables DVC charts beside the predictions
    assert sorted(path.name for path in (tmp_path / "plots").iterdir()) == [
        "depth_examples.png", "errors_per_frame.png", "trajectory_O1.png"]
    for name in ("per_frame.csv", "per_sequence.csv", "trajectory.csv"):
        assert (tmp_path / "predictions" / name).is_file(), name
    assert len(pd.read_csv(tmp_path / "predictions" / "per_frame.csv")) == FRAMES
    assert len(list((tmp_path / "predictions").rglob("*.npy"))) == FRAMES
    assert not list(tmp_path.glob(".*partial*"))

    run = tracking.client(uri).get_run(run_id)
    # the headline as metrics, the runs table's columns; every figure in one table, not as one-point charts
    headline = {"test/simcol_3/abs_rel": written["depth_paper"]["model"]["abs_rel"],
                "test/simcol_3/rte_cm": written["pose_simcol"]["model"]["rte"],
                "test/simcol_3/rot_deg": written["pose_simcol"]["model"]["rot"]}
    assert run.data.metrics == pytest.approx(headline)
    view = json.loads(tracking.client(uri).get_experiment(run.info.experiment_id).tags[tracking.RUNS_VIEW_TAG])
    assert [f"metrics.`{key}`" for key in headline] == view["selectedColumns"][1:]
    artifacts = [a.path for a in tracking.client(uri).list_artifacts(run_id, "eval/simcol_3")]
    assert {"eval/simcol_3/trajectory_O1.png", "eval/simcol_3/figures.csv"} <= set(artifacts)
    table = pd.read_csv(tracking.client(uri).download_artifacts(run_id, "eval/simcol_3/figures.csv", str(tmp_path)))
    assert len(table) == sum(len(figures) for protocol in PROTOCOLS for figures in written[protocol].values())
    model_abs_rel = table.query("protocol == 'depth_paper' and method == 'model' and metric == 'abs_rel'")
    assert model_abs_rel["value"].tolist() == pytest.approx([written["depth_paper"]["model"]["abs_rel"]])
    # the test set beside the training shards, though both are the same folder (one manifest, one digest)
    inputs = {i.dataset.name: (i.dataset.digest, [(t.key, t.value) for t in i.tags]) for i in run.inputs.dataset_inputs}
    assert inputs == {"simcol": (file_sha256(manifest)[:32], [("mlflow.data.context", "training")]),
                      "simcol_3": (file_sha256(manifest)[:32], [("mlflow.data.context", "evaluation")])}


def test_a_model_whose_training_run_is_not_in_the_store_logs_into_one_new_run_with_a_warning(
        oracle_shards: Path, tmp_path: Path, capsys: pytest.CaptureFixture):
    """A model file copied from another machine names a run this store lacks: evaluating it used to fail with
    MLflow's "Run with id ... not found"."""
    from endoflow.evaluation.evaluate import log_evaluation

    params = shard_params(oracle_shards)
    params.model = params.model.replace(latent_bank=False)
    write_untrained_model(tmp_path / "endoflow.pt", params, "0123456789abcdef0123456789abcdef")
    urls = eval_set_shards(str(oracle_shards), params.eval.test_sets["simcol_3"])
    result = evaluate_test_set(params, "simcol_3", urls, tmp_path / "endoflow.pt", tmp_path / "m.json",
                               tmp_path / "plots", tmp_path / "predictions")
    log_evaluation(params, tmp_path, result, tmp_path / "plots")
    assert "0123456789abcdef0123456789abcdef is not in sqlite:///" in capsys.readouterr().err
    log_evaluation(params, tmp_path, result | {"test_set": "simcol_12"}, tmp_path / "plots")  # a second test set
    assert "warning" not in capsys.readouterr().err

    uri = tracking.tracking_uri(params, tmp_path)
    experiment = tracking.client(uri).get_experiment_by_name(params.tracking.experiment)
    runs = tracking.client(uri).search_runs([experiment.experiment_id])
    assert len(runs) == 1
    assert runs[0].data.tags[tracking.MODEL_RUN_TAG] == "0123456789abcdef0123456789abcdef"
    assert {"test/simcol_3/abs_rel", "test/simcol_12/abs_rel"} <= set(runs[0].data.metrics)


def target_sample(frame: int, sequence: str = "S1") -> dict:
    """A decoded triplet sample of ``frame`` with neighbours frame -/+ 1 and identity poses."""
    pose = np.eye(4).tolist()
    meta = {"sequence": sequence, "group": "g", "frame": frame, "split": "test", "native_size": [8, 8],
            "K": [[8.0, 0.0, 3.5], [0.0, 8.0, 3.5], [0.0, 0.0, 1.0]],
            "frame_ids": {"prev": frame - 1, "cur": frame, "next": frame + 1},
            "T_world_cam": {"prev": pose, "cur": pose, "next": pose}, "dataset": "simcol", "intrinsics_known": True}
    image = torch.zeros(3, 8, 8)
    return {"meta": meta, "prev": image, "cur": image, "next": image, "depth": torch.ones(1, 8, 8)}


def test_frames_on_both_sides_of_missing_frames_are_evaluated_and_never_paired_across_the_gap() -> None:
    # frames 1..8 with frame 4 missing: targets 2 | 6 7 (no triplet spans the gap)
    frames = list(frames_in_order([target_sample(2), target_sample(6), target_sample(7)]))
    assert [f.frame for f in frames] == [1, 2, 3, 5, 6, 7, 8]
    assert [f.frame for f in frames if f.after_gap] == [5]
    poses = [np.eye(4)] * 7
    assert longest_posed_run(poses, gaps={3}) == (3, 7)  # frames 5..8, not 1..8 across the gap
    assert longest_posed_run(poses) == (0, 7)


def test_the_sequence_reader_refuses_frames_out_of_temporal_order() -> None:
    with pytest.raises(ValueError, match="sequence S1: frame 2 follows frame 3; test shards must hold frames in "
                                         "temporal order"):
        list(frames_in_order([target_sample(3), target_sample(2)]))


def test_the_sequence_reader_gives_each_kept_sequence_whole_and_in_order(oracle_shards: Path) -> None:
    urls = eval_set_shards(str(oracle_shards), EvalSetConfig(dataset="simcol"))
    frames = list(sequence_frames(urls, lambda meta: meta["sequence"] in ("S5", "O1"), max_frames=3))
    # three targets (frames 1..3) and the first one's prev; the last one's next is frame 4
    assert [(f.sequence, f.frame) for f in frames] == [(s, i) for s in ("S5", "O1") for i in range(5)]
    assert [f.depth_cm is not None for f in frames[:5]] == [False, True, True, True, False]


def test_without_refinement_the_evaluation_has_no_refined_path_and_writes_every_table(oracle_shards: Path,
                                                                                        tmp_path: Path):
    params = shard_params(oracle_shards)
    params.model = params.model.replace(latent_bank=False)
    params.refine = params.refine.replace(enabled=False)
    write_untrained_model(tmp_path / "endoflow.pt", params, None)
    urls = eval_set_shards(str(oracle_shards), params.eval.test_sets["simcol_3"])
    result = evaluate_test_set(params, "simcol_3", urls, tmp_path / "endoflow.pt", tmp_path / "m.json",
                               tmp_path / "plots", tmp_path / "predictions")
    assert set(result["pose_simcol"]) == {"model", "constant_velocity"}
    columns = (tmp_path / "predictions" / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert "model_x" in columns and not any(column.startswith("refined") for column in columns)
    assert (tmp_path / "plots" / "trajectory_O1.png").is_file()


def test_a_test_set_of_unlabelled_video_is_refused_saying_why():
    from endoflow.config import EvalSetConfig
    from endoflow.evaluation.evaluate import belongs_to

    test_set = EvalSetConfig(dataset="video")
    meta = {"split": "test", "group": "video", "sequence": "clip", "dataset": "video",
            "ground_truth": {"depth": False, "pose": False}}
    with pytest.raises(ValueError, match="sequence clip has no ground-truth depth or poses .* photometric error"):
        belongs_to(meta, test_set)
    assert not belongs_to({**meta, "split": "train"}, test_set)  # not of the test set: not looked at
    assert belongs_to({**meta, "ground_truth": {"depth": True, "pose": False}}, test_set)
