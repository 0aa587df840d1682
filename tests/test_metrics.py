"""Evaluation metrics against values worked out by hand on tiny arrays, in every protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest

from endoflow.evaluation import metrics
from endoflow.geometry.pose import motion_statistics


def translation(x: float, y: float, z: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def rotation_z(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    return pose


def rotation_y(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    pose = np.eye(4)
    pose[[0, 0, 2, 2], [0, 2, 0, 2]] = [c, s, -s, c]
    return pose


def curved_trajectory(n: int = 12) -> np.ndarray:
    """A camera moving forward while turning and rising: non-trivial rotations and translations."""
    poses = [translation(3.0, -1.0, 2.0) @ rotation_y(30.0)]
    for i in range(n - 1):
        step = translation(0.1 * i, 0.05, 1.0) @ rotation_y(4.0 + i) @ rotation_z(2.0)
        poses.append(poses[-1] @ step)
    return np.stack(poses)


# ---------------------------------------------------------------------------------- paper depth
def test_paper_protocol_hand_computed_errors_on_masked_pixels():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # the 0 is unknown and must be ignored
    pred = np.array([[1.0, 2.0], [2.0, 99.0]])  # medians 2 and 2: ratio 1; errors 0, 0, 2
    errors = metrics.paper_depth_errors(gt, pred)
    assert errors["ratio"] == pytest.approx(1.0)
    assert errors["abs_rel"] == pytest.approx((2 / 4) / 3)
    assert errors["sq_rel"] == pytest.approx((4 / 4) / 3)
    assert errors["rmse"] == pytest.approx(math.sqrt(4 / 3))
    assert errors["rmse_log"] == pytest.approx(math.log(2) / math.sqrt(3))
    assert errors["l1"] == pytest.approx(2 / 3)
    # the third pixel is off by a factor 2 > 1.25^3 = 1.95: it fails every threshold
    assert (errors["a1"], errors["a2"], errors["a3"]) == pytest.approx((2 / 3, 2 / 3, 2 / 3))


def test_paper_protocol_median_scaling_makes_a_scaled_prediction_exact():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])
    errors = metrics.paper_depth_errors(gt, 7.0 * np.where(gt > 0, gt, 5.0))
    assert errors["ratio"] == pytest.approx(1 / 7)
    assert errors["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert errors["a1"] == 1.0


def test_paper_protocol_clamps_the_scaled_prediction_to_20_cm():
    gt = np.array([[10.0, 10.0, 10.0]])
    pred = np.array([[1.0, 1.0, 5.0]])  # ratio 10: the last pixel becomes 50 cm, clamped to 20
    errors = metrics.paper_depth_errors(gt, pred)
    assert errors["l1"] == pytest.approx(10 / 3)


def test_paper_protocol_shape_ratios_compare_the_nearest_and_farthest_tenth_after_the_scaling():
    # GT 1..20 cm; the prediction right up to 10 cm and compressed beyond it, as a depth that flattens the far end
    gt = np.arange(1.0, 21.0).reshape(4, 5)
    pred = np.where(gt <= 10, gt, 10 + (gt - 10) / 2)
    errors = metrics.paper_depth_errors(gt, pred)
    scale = errors["ratio"]  # median(gt) 10.5 over median(pred) 10.25
    assert scale == pytest.approx(10.5 / 10.25)
    # the nearest tenth (1 and 2 cm, at or below the 0.1 quantile 2.9) and the farthest (19 and 20 cm, at or above 18.1)
    assert errors["near_ratio"] == pytest.approx(1 / scale)
    assert errors["far_ratio"] == pytest.approx(np.median([19 / 14.5, 20 / 15]) / scale)
    exact = metrics.paper_depth_errors(gt, 3 * gt)
    assert exact["near_ratio"] == pytest.approx(1.0) and exact["far_ratio"] == pytest.approx(1.0)


def test_shape_ratios_take_every_pixel_tied_at_a_quantile_into_its_tenth():
    # GT saturated at its far end: a quarter of the pixels at 20 cm, all of them at the 0.9 quantile
    gt = np.concatenate([np.arange(1.0, 16.0), np.full(5, 20.0)])
    pred = np.where(gt < 20, gt, 16.0)
    assert metrics.shape_ratios(gt, pred)["far_ratio"] == pytest.approx(20 / 16)  # the five, not the top two
    flat = np.full(10, 5.0)  # one depth everywhere: both tenths are every pixel
    ratios = metrics.shape_ratios(flat, flat * np.linspace(0.8, 1.2, 10))
    assert ratios["near_ratio"] == ratios["far_ratio"] == pytest.approx(np.median(1 / np.linspace(0.8, 1.2, 10)))


def test_paper_protocol_rejects_mismatched_or_empty_maps():
    with pytest.raises(ValueError, match=r"pred_cm: expected shape \[H, W\] with H=2, W=2, got \(2, 3\)"):
        metrics.paper_depth_errors(np.ones((2, 2)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="no valid"):
        metrics.paper_depth_errors(np.zeros((2, 2)), np.ones((2, 2)))


# --------------------------------------------------------------------------------- simcol depth
def test_simcol_depth_protocol_one_scale_per_sequence_hand_computed():
    gt = np.array([[[3.0, 5.0]], [[8.0, 8.0]]])  # image means 4 and 8 cm
    pred = np.array([[[1.0, 3.0]], [[4.0, 4.0]]])  # image means 2 and 4 cm: the scale is exactly 2
    result = metrics.simcol_depth_sequence(pred, gt)
    assert result["scale"] == pytest.approx(2.0)
    # frame 0: 2*pred = [2, 6] against [3, 5]; frame 1 exact
    frame0_rel = np.median([1 / (3 + 1e-4), 1 / (5 + 1e-4)]) * 100
    np.testing.assert_allclose(result["per_frame"]["l1"], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(result["per_frame"]["rmse"], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(result["per_frame"]["rel"], [frame0_rel, 0.0], atol=1e-9)
    assert result["l1"] == pytest.approx(0.5)
    assert result["rel"] == pytest.approx(frame0_rel / 2)
    assert result["rmse"] == pytest.approx(0.5)


def test_simcol_depth_protocol_clips_predictions_beyond_20_cm_before_scaling():
    gt = np.full((1, 1, 2), 10.0)
    pred = np.array([[[10.0, 35.0]]])  # 35 cm -> 1.0 in the challenge encoding, i.e. 20 cm
    assert metrics.simcol_depth_scale(metrics.depth_to_simcol_unit(pred), gt) == pytest.approx(
        0.5 / 0.75)
    result = metrics.simcol_depth_sequence(pred, gt)
    s = 0.5 / 0.75
    assert result["l1"] == pytest.approx((abs(10 * s - 10) + abs(20 * s - 10)) / 2)


# ---------------------------------------------------------------------------------- simcol pose
def test_simcol_pose_exact_recovery_gives_zero_error():
    gt = curved_trajectory()
    result = metrics.simcol_pose_sequence(gt, metrics.relative_poses(gt))
    assert result["scale"] == pytest.approx(1.0)
    for key in metrics.SIMCOL_POSE_KEYS:
        assert result[key] == pytest.approx(0.0, abs=1e-6), key
    np.testing.assert_allclose(result["trajectory"], gt, atol=1e-9)


def test_simcol_pose_scaled_prediction_is_exact_after_the_scale_fit():
    gt = curved_trajectory()
    predicted = metrics.scaled_relative_poses(metrics.relative_poses(gt), 0.25)
    result = metrics.simcol_pose_sequence(gt, predicted)
    assert result["scale"] == pytest.approx(4.0)
    for key in ("ate_local", "rte", "rot"):
        assert result[key] == pytest.approx(0.0, abs=1e-6), key
    # the challenge's ATE scales the chain's absolute positions: 4 (t_0 + (t_i - t_0) / 4) = t_i + 3 t_0, so every
    # frame is off by 3 |t_0|, P_0 being (3, -1, 2) cm from the world origin
    np.testing.assert_allclose(result["per_frame"]["ate"], 3 * math.sqrt(14.0), rtol=1e-9)


def test_simcol_pose_hand_computed_straight_line():
    gt = np.stack([translation(0, 0, z) for z in (0.0, 1.0, 2.0)])
    predicted = np.stack([translation(0, 0, 1.0), translation(0, 0, 2.0)])
    result = metrics.simcol_pose_sequence(gt, predicted)
    assert result["scale"] == pytest.approx(0.6)  # (1*1 + 1*2) / (1 + 4)
    np.testing.assert_allclose(result["per_frame"]["rte"], [0.4, 0.2], atol=1e-12)
    np.testing.assert_allclose(result["per_frame"]["ate"], [0.0, 0.4, 0.2], atol=1e-12)
    assert result["rte"] == pytest.approx(0.3)
    assert result["ate"] == result["ate_local"] == pytest.approx(0.2)  # P_0 at the origin: both ATEs agree
    assert result["rot"] == pytest.approx(0.0, abs=1e-6)


def test_simcol_challenge_ate_scales_the_first_poses_offset_from_the_origin_and_ate_local_does_not():
    gt = np.stack([translation(0, 0, z) for z in (10.0, 11.0, 12.0)])
    predicted = np.stack([translation(0, 0, 1.0), translation(0, 0, 2.0)])
    result = metrics.simcol_pose_sequence(gt, predicted)
    assert result["scale"] == pytest.approx(0.6)
    # the challenge: chain from P_0 (z = 10, 11, 13), times 0.6 (6, 6.6, 7.8), against 10, 11, 12
    np.testing.assert_allclose(result["per_frame"]["ate"], [4.0, 4.4, 4.2], atol=1e-12)
    assert result["ate"] == pytest.approx(4.2)
    # ours: the scaled steps chained from P_0 (10, 10.6, 11.8)
    np.testing.assert_allclose(result["per_frame"]["ate_local"], [0.0, 0.4, 0.2], atol=1e-12)
    assert result["ate_local"] == pytest.approx(0.2)


def test_simcol_pose_rotation_error_in_degrees():
    gt = np.stack([translation(0, 0, z) for z in (0.0, 1.0, 2.0)])
    predicted = np.stack([translation(0, 0, 1.0) @ rotation_z(10.0)] * 2)
    result = metrics.simcol_pose_sequence(gt, predicted)
    np.testing.assert_allclose(result["per_frame"]["rot"], [10.0, 10.0], atol=1e-9)
    np.testing.assert_allclose(result["per_frame"]["rte"], [0.0, 0.0], atol=1e-12)


def test_pose_metrics_do_not_depend_on_the_world_frame():
    gt = curved_trajectory()
    noisy = metrics.relative_poses(gt) @ rotation_z(1.5) @ translation(0.02, -0.01, 0.03)
    world_change = translation(-7.0, 2.0, 11.0) @ rotation_y(-70.0) @ rotation_z(25.0)
    base = metrics.simcol_pose_sequence(gt, noisy)
    moved = metrics.simcol_pose_sequence(world_change @ gt, noisy)
    for key in ("ate_local", "rte", "rot"):
        assert moved[key] == pytest.approx(base[key], rel=1e-9), key
    assert abs(moved["ate"] - base["ate"]) > 0.01  # the challenge's ATE alone depends on the world origin
    assert base["rte"] > 0.01 and base["rot"] > 1.0
    endoslam_base = metrics.endoslam_pose_sequence(gt, noisy)
    endoslam_moved = metrics.endoslam_pose_sequence(world_change @ gt, noisy)
    for key in metrics.ENDOSLAM_POSE_KEYS:
        assert endoslam_moved[key] == pytest.approx(endoslam_base[key], rel=1e-9), key


def test_pose_protocols_reject_wrong_shapes_and_counts():
    gt = curved_trajectory(4)
    with pytest.raises(ValueError, match="expected 3 relative poses"):
        metrics.simcol_pose_sequence(gt, metrics.relative_poses(gt)[:2])
    with pytest.raises(ValueError, match=r"GT poses: expected shape \[N, 4, 4\], got \(4, 3, 4\)"):
        metrics.endoslam_pose_sequence(gt[:, :3], metrics.relative_poses(gt))


# -------------------------------------------------------------------------------- endoslam pose
def test_endoslam_pose_hand_computed_straight_line():
    gt = np.stack([translation(0, 0, z) for z in (0.0, 1.0, 2.0)])
    predicted = np.stack([translation(0, 0, 1.0), translation(0, 0, 2.0)])  # positions 0, 1, 3
    result = metrics.endoslam_pose_sequence(gt, predicted)
    assert result["scale"] == pytest.approx(0.7)  # (1*1 + 2*3) / (1 + 9)
    assert result["ate"] == pytest.approx(math.sqrt((0.3**2 + 0.1**2) / 3))
    assert result["rpe_trans"] == pytest.approx((0.3 + 0.4) / 2)
    assert result["rpe_rot"] == pytest.approx(0.0, abs=1e-6)


def test_endoslam_pose_exact_and_scaled_recovery():
    gt = curved_trajectory()
    scaled = metrics.scaled_relative_poses(metrics.relative_poses(gt), 3.0)
    result = metrics.endoslam_pose_sequence(gt, scaled)
    assert result["scale"] == pytest.approx(1 / 3)
    for key in metrics.ENDOSLAM_POSE_KEYS:
        assert result[key] == pytest.approx(0.0, abs=1e-6), key


def test_mean_over_averages_each_key_and_refuses_nothing():
    assert metrics.mean_over([{"a": 1.0, "b": 4.0}, {"a": 3.0, "b": 0.0}], ("a",)) == {"a": 2.0}
    with pytest.raises(ValueError, match="nothing to average"):
        metrics.mean_over([], ("a",))


# --------------------------------------------------------------------------------- motion statistics
def test_motion_statistics_of_constant_velocity_have_no_change():
    step = translation(0, 0, 0.135) @ rotation_y(0.1)
    poses = [translation(5.0, -3.0, 28.0) @ rotation_z(40.0)]
    for _ in range(9):
        poses.append(poses[-1] @ step)
    stats = motion_statistics(np.stack(poses))
    assert stats["step_mm"] == pytest.approx(1.35)
    assert stats["rotation_deg"] == pytest.approx(0.1)
    assert stats["step_change_mm"] == pytest.approx(0.0, abs=1e-9)
    assert stats["rotation_change_deg"] == pytest.approx(0.0, abs=1e-5)
    assert stats["forward_share"] == 1.0


def test_motion_statistics_hand_computed_changes_and_a_backward_step():
    steps = [translation(0, 0, 0.1), translation(0, 0, 0.12) @ rotation_z(2.0), translation(0, 0, -0.1)]
    poses = [np.eye(4)]
    for step in steps:
        poses.append(poses[-1] @ step)
    stats = motion_statistics(np.stack(poses))
    assert stats["step_mm"] == pytest.approx(1.0)  # median of 1.0, 1.2, 1.0 mm
    assert stats["rotation_deg"] == pytest.approx(0.0, abs=1e-6)  # median of 0, 2, 0
    assert stats["step_change_mm"] == pytest.approx((0.2 + 2.2) / 2)  # |0.12 - 0.1|, |-0.1 - 0.12| cm
    assert stats["rotation_change_deg"] == pytest.approx(2.0)  # 0 -> 2 -> 0 degrees
    assert stats["forward_share"] == pytest.approx(2 / 3)


def path_of(steps: list[np.ndarray]) -> np.ndarray:
    """Camera-to-world poses from ``P_0 = I`` by the relative steps ``Q_i``."""
    return metrics.chain_relative_poses(np.eye(4), np.stack(steps))


def test_motion_agreement_of_an_exact_or_scaled_prediction_is_perfect():
    truth = path_of([translation(0.1 * i, 0.05, 0.5 + 0.3 * math.sin(i)) @ rotation_y(4.0 + i) @ rotation_z(2.0)
                     for i in range(11)])
    relative = metrics.relative_poses(truth)
    for scale in (1.0, 0.3):
        figures = metrics.motion_agreement(truth, metrics.scaled_relative_poses(relative, scale))
        assert figures["step_corr"] == pytest.approx(1.0)
        assert figures["forward_corr"] == pytest.approx(1.0)
        assert figures["rotation_corr"] == pytest.approx(1.0)
        assert figures["step_spread"] == pytest.approx(1.0)
        assert figures["direction_deg"] == pytest.approx(0.0, abs=1e-5)


def test_motion_agreement_of_a_constant_step_follows_nothing():
    truth = path_of([translation(0, 0, z) @ rotation_y(a) for z, a in ((1, 1), (2, 3), (3, 2), (0.5, 4))])
    constant = np.repeat((translation(0, 0, 1.5) @ rotation_y(2.5))[None], 4, axis=0)
    figures = metrics.motion_agreement(truth, constant)
    assert figures["step_corr"] == figures["forward_corr"] == figures["rotation_corr"] == 0.0
    assert figures["step_spread"] == 0.0
    assert figures["direction_deg"] == pytest.approx(0.0, abs=1e-6)  # every true step points forward too


def test_motion_agreement_hand_computed():
    # true steps 1, 2, 3 cm forward; predicted 1, 1, 2: correlation 1 / (sqrt(2) sqrt(6) / 3) = 0.8660
    truth = path_of([translation(0, 0, z) for z in (1, 2, 3)])
    predicted = np.stack([translation(0, 0, z) for z in (1, 1, 2)])
    figures = metrics.motion_agreement(truth, predicted)
    assert figures["step_corr"] == pytest.approx(3 / math.sqrt(12))
    assert figures["forward_corr"] == pytest.approx(3 / math.sqrt(12))
    assert figures["rotation_corr"] == 0.0  # neither side turns
    # scale fit sum(gt.pred) / sum(pred^2) = (1 + 2 + 6) / 6 = 1.5; std(1.5 * [1, 1, 2]) / std([1, 2, 3])
    assert figures["step_spread"] == pytest.approx(1.5 * np.std([1, 1, 2]) / np.std([1, 2, 3]))


def test_motion_agreement_signs_and_directions():
    truth = path_of([translation(0, 0, z) for z in (1, -1, 2, -2)])  # forward, back, forward, back
    backwards = np.stack([translation(0, 0, -z) for z in (1, -1, 2, -2)])
    assert metrics.motion_agreement(truth, backwards)["forward_corr"] == pytest.approx(-1.0)
    assert metrics.motion_agreement(truth, backwards)["step_corr"] == pytest.approx(1.0)  # lengths agree
    sideways = np.stack([translation(z, 0, 0) for z in (1, -1, 2, -2)])
    assert metrics.motion_agreement(truth, sideways)["direction_deg"] == pytest.approx(90.0)


def test_motion_agreement_leaves_the_direction_of_a_pausing_camera_out():
    # the 1e-4 cm step (a pause) points sideways in the prediction; the moving steps agree exactly
    truth = path_of([translation(0, 0, z) for z in (1, 1e-4, 2, 1)])
    predicted = np.stack([translation(0, 0, 1), translation(1e-4, 0, 0), translation(0, 0, 2), translation(0, 0, 1)])
    assert metrics.motion_agreement(truth, predicted)["direction_deg"] == pytest.approx(0.0, abs=1e-6)


def test_motion_agreement_needs_two_steps():
    truth = path_of([translation(0, 0, 1)])
    with pytest.raises(ValueError, match="at least 2"):
        metrics.motion_agreement(truth, metrics.relative_poses(truth))


def test_scale_consistency_of_a_path_and_depth_at_one_scale_is_one():
    truth = path_of([translation(0, 0, z) for z in (1, 2, 3, 2)])
    half = metrics.scaled_relative_poses(metrics.relative_poses(truth), 0.5)  # GT = 2 x predicted path
    figures = metrics.scale_consistency(truth, half, [2.0] * 5)  # GT = 2 x predicted depth in every frame
    assert figures == pytest.approx({"path_over_depth": 1.0, "depth_drift": 1.0})


def test_scale_consistency_hand_computed():
    truth = path_of([translation(0, 0, z) for z in (1, 2, 3, 2)])
    half = metrics.scaled_relative_poses(metrics.relative_poses(truth), 0.5)
    # depth scaling 1.0 1.0 1.5 2.0 2.0 3.0 3.0 3.0: median 2.0; quarters (2 frames) 1.0 and 3.0
    figures = metrics.scale_consistency(truth, half, [1.0, 1.0, 1.5, 2.0, 2.0, 3.0, 3.0, 3.0])
    assert figures["path_over_depth"] == pytest.approx(2.0 / 2.0)
    assert figures["depth_drift"] == pytest.approx(3.0)
    assert metrics.scale_consistency(truth, half, [4.0] * 5)["path_over_depth"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="positive"):
        metrics.scale_consistency(truth, half, [])


def test_the_direction_of_a_camera_that_mostly_pauses_comes_from_its_moving_steps():
    # three of five steps exactly still (their median is 0): the two moving steps agree exactly
    truth = path_of([translation(0, 0, z) for z in (0, 0, 1, 0, 2)])
    predicted = np.stack([translation(x, 0, z) for x, z in ((1e-3, 0), (0, 1e-3), (0, 1), (1e-3, 0), (0, 2))])
    assert metrics.motion_agreement(truth, predicted)["direction_deg"] == pytest.approx(0.0, abs=1e-6)
    still = path_of([translation(0, 0, 0)] * 3)
    assert metrics.motion_agreement(still, metrics.relative_poses(still))["direction_deg"] == 0.0


def test_scale_consistency_refuses_paths_it_cannot_compare():
    truth = path_of([translation(0, 0, z) for z in (1, 2, 3)])
    with pytest.raises(ValueError, match="expected 3 relative poses"):
        metrics.scale_consistency(truth, metrics.relative_poses(truth)[:1], [1.0] * 4)
    with pytest.raises(ValueError, match="does not move"):
        metrics.scale_consistency(truth, np.repeat(np.eye(4)[None], 3, axis=0), [1.0] * 4)
