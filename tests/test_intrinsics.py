"""Intrinsics learned from video: a camera nobody calibrated starts from an assumed K, the view-synthesis loss
corrects it, calibrated cameras keep theirs, and shards can withhold K to measure what is learned."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from endoflow.config import DATASETS, LossConfig, Params
from endoflow.data.frame_encoding import stored_intrinsics
from endoflow.data.intrinsics import assumed_intrinsics
from endoflow.data.loader import raw_samples
from endoflow.data.shard_format import decode_sample
from endoflow.data.shards import write_dataset_shards
from endoflow.models.endoflow_model import build_model, load_trained_model
from endoflow.models.intrinsics import CameraIntrinsics
from endoflow.models.model_file import ModelRecord, TrainingBaselines, save_model_file
from endoflow.geometry.pose import pose_vec_to_matrix, relative_pose
from endoflow.synth.render import render_tube_frame
from endoflow.synth.scenes import STYLES, make_tube_sequence
from endoflow.synth.writers import simcol_intrinsics
from endoflow.training.objective import reprojection
from tests.test_shards import SyntheticSource, small_params


def test_an_untrained_camera_is_the_assumed_one_and_a_calibrated_one_is_left_alone():
    cameras = CameraIntrinsics(len(DATASETS))
    K = torch.tensor([[20.0, 0, 15.5], [0, 20.0, 15.5], [0, 0, 1]]).expand(2, 3, 3)
    camera = torch.tensor([DATASETS.index("video")] * 2)
    assert torch.equal(cameras(K, camera, torch.tensor([False, True]), (32, 32)), K)
    with torch.no_grad():
        cameras.corrections[DATASETS.index("video")] = torch.tensor([np.log(1.5), np.log(2.0), 0.25, -0.125])
    learned = cameras(K, camera, torch.tensor([False, True]), (32, 32))
    torch.testing.assert_close(learned[0], torch.tensor([[30.0, 0, 23.5], [0, 40.0, 11.5], [0, 0, 1]]))
    assert torch.equal(learned[1], K[1])
    assert cameras.learned(DATASETS.index("video")) and not cameras.learned(DATASETS.index("simcol"))
    known = cameras(K, camera, torch.tensor([True, True]), (32, 32))
    assert not known.requires_grad  # all calibrated: no graph through the corrections


def test_with_the_principal_point_held_only_the_focal_lengths_learn_and_switching_back_frees_it():
    cameras = CameraIntrinsics(len(DATASETS))
    K = torch.tensor([[20.0, 0, 15.5], [0, 20.0, 15.5], [0, 0, 1]]).expand(2, 3, 3)
    camera = torch.tensor([DATASETS.index("video")] * 2)
    unknown = torch.tensor([False, False])
    optimiser = torch.optim.Adam(cameras.parameters(), lr=0.1)

    def step() -> torch.Tensor:
        optimiser.zero_grad()
        cameras(K, camera, unknown, (32, 32)).sum().backward()  # every entry of K pulled down
        optimiser.step()
        return cameras.corrections.detach()[DATASETS.index("video")].clone()

    cameras.learn(True, principal_point=False)
    held = step()
    assert held[0] < 0 and held[1] < 0 and torch.equal(held[2:], torch.zeros(2))
    cameras.learn(True)
    freed = step()
    assert freed[2] < 0 and freed[3] < 0
    cameras.learn(False)
    assert not cameras.corrections.requires_grad


def rendered_triplets(lateral: bool, size: int = 64) -> dict[str, torch.Tensor]:
    """Built-in colon frames with exact depth, poses and K: the camera moving forward, or (``lateral``) also
    sideways and turning, as triplets."""
    sequence = make_tube_sequence(STYLES["SyntheticColon_I"], 12, np.random.default_rng(3), torch.device("cpu"))
    K = simcol_intrinsics(size)
    step = [0.015, 0.02, 0.0, 0.06, 0.04, 0.1] if lateral else [0.0, 0.0, 0.0, 0.0, 0.0, 0.1]
    poses = [sequence.poses[4] @ pose_vec_to_matrix(torch.tensor(step, dtype=torch.float64) * i).numpy()
             for i in range(6)]
    rendered = [render_tube_frame(sequence.scene, pose, K, size, size) for pose in poses]
    rgb = torch.stack([torch.from_numpy(np.asarray(r, np.float32)).permute(2, 0, 1) for r, _ in rendered]).clamp(0, 1)
    depth = torch.stack([torch.from_numpy(np.asarray(d, np.float32))[None] for _, d in rendered])
    cur = range(1, 5)
    return {"prev": rgb[[c - 1 for c in cur]], "cur": rgb[list(cur)], "next": rgb[[c + 1 for c in cur]],
            "depth": depth[list(cur)], "K": torch.from_numpy(K).float().expand(len(cur), 3, 3).clone(),
            "T_prev_cur": torch.from_numpy(np.stack([relative_pose(poses[c - 1], poses[c]) for c in cur])).float(),
            "T_next_cur": torch.from_numpy(np.stack([relative_pose(poses[c + 1], poses[c]) for c in cur])).float()}


def loss_at(batch: dict, K: torch.Tensor) -> torch.Tensor:
    return reprojection(batch["cur"], [batch["prev"], batch["next"]], batch["depth"],
                        [batch["T_prev_cur"], batch["T_next_cur"]], K, LossConfig())


def test_the_view_synthesis_loss_recovers_a_focal_length_assumed_a_third_too_short():
    """Exact depth and motion, sideways and turning on both axes: only K is wrong, and the photometric loss finds
    it (each focal length needs motion across its own axis)."""
    batch = rendered_triplets(lateral=True)
    size = tuple(batch["cur"].shape[-2:])
    truth = batch["K"][0]
    wrong = truth.clone()
    wrong[:2, :2] *= 0.7
    wrong[0, 2] += 2.0  # px off the true principal point
    cameras = CameraIntrinsics(1)
    optimiser = torch.optim.Adam(cameras.parameters(), lr=1e-2)
    camera, unknown = torch.zeros(len(batch["cur"]), dtype=torch.long), torch.zeros(len(batch["cur"]), dtype=bool)
    for _ in range(150):
        loss = loss_at(batch, cameras(wrong.expand_as(batch["K"]), camera, unknown, size))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    learned = cameras(wrong[None], camera[:1], unknown[:1], size)[0].detach()
    assert learned[0, 0] == pytest.approx(float(truth[0, 0]), rel=0.05)
    assert learned[1, 1] == pytest.approx(float(truth[1, 1]), rel=0.05)
    assert learned[0, 2] == pytest.approx(float(truth[0, 2]), abs=1.0)
    assert learned[1, 2] == pytest.approx(float(truth[1, 2]), abs=1.0)


def test_moving_straight_ahead_says_nothing_about_the_focal_length():
    """Forward motion moves a pixel along its ray from the centre by Z / (Z + t) whatever the focal length: the
    loss is flat in it (docs/method.md, "Intrinsics learned from the video")."""
    batch = rendered_triplets(lateral=False)
    losses = []
    for factor in (0.8, 1.0, 1.25):
        K = batch["K"].clone()
        K[:, :2, :2] *= factor
        losses.append(float(loss_at(batch, K)))
    assert max(losses) < 1.01 * min(losses)


def test_withheld_intrinsics_are_stored_as_the_assumed_K_and_marked_unknown(tmp_path: Path):
    params = small_params()
    params.preprocess = params.preprocess.replace(withhold_intrinsics=True)
    source = SyntheticSource()
    write_dataset_shards(source, "simcol", params, tmp_path / "simcol")
    sample = decode_sample(next(raw_samples(sorted(str(p) for p in (tmp_path / "simcol").glob("train-*.tar")))))
    sequence = source()[0]
    assert not bool(sample["intrinsics_known"]) and int(sample["camera"]) == DATASETS.index("simcol")
    # the native 48 x 64 frames' assumed K (140 degrees across their diagonal), after the crop and resize
    assumed = assumed_intrinsics(sequence.image_size, params.data.assumed_fov_deg)
    np.testing.assert_allclose(sample["K"].numpy(), stored_intrinsics(assumed, sequence.image_size, 32), atol=1e-4)
    assert not np.allclose(sample["K"].numpy(), stored_intrinsics(sequence.K, sequence.image_size, 32), atol=1)


def test_a_model_file_from_before_learned_intrinsics_loads_with_every_camera_as_assumed(tmp_path: Path):
    params = Params()
    model = build_model(params, None)
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("intrinsics.")}
    path = tmp_path / "old.pt"
    save_model_file(path, ModelRecord(params, state, 1, {}, None, TrainingBaselines(1.0, np.ones((4, 4), np.float32),
                                                                                   np.eye(4))))
    loaded, _ = load_trained_model(path, torch.device("cpu"))
    assert not loaded.intrinsics.corrections.any()
