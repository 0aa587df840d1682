"""Direct photometric alignment and the keyframe tracker on rendered frames with their exact depth: they recover a
known motion, never end worse than they start, and ignore a black field-of-view border."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from endoflow.config import Params, RefineConfig
from endoflow.evaluation import metrics
from endoflow.geometry import alignment_loops, direct_alignment
from endoflow.geometry.direct_alignment import (
    AlignmentSettings,
    KeyframeTracker,
    TrackerSettings,
    align_to_keyframe,
    tracker_settings,
)
from endoflow.geometry.pose import mean_step, pose_vec_to_matrix, relative_pose, rotation_angle_deg
from endoflow.synth.render import render_tube_frame
from endoflow.synth.writers import plan_jobs, simcol_intrinsics, tube_sequence

SIZE = 64
FRAMES = 40
# exact depth: the light's fall-off with distance (inverse-square through the renderer's gamma 2.2) holds; the
# rotation free, since these starts are off the truth on purpose (the prior's tests set it)
EXACT = AlignmentSettings(light_falloff=0.91, rotation_prior=0.0)


@pytest.fixture(scope="module")
def rendered() -> dict:
    """The first frames of the built-in test sequence S5 (a slow advance, then a pause) at 64 px, exact depth."""
    params = Params()
    job = next(job for job in plan_jobs("simcol", Path("unused"), 5, 60, SIZE, 0, "cpu", params, test_frames=120)
               if job.name == "S5")
    sequence = tube_sequence(job)
    K = simcol_intrinsics(SIZE)
    frames = [render_tube_frame(sequence.scene, pose, K, SIZE, SIZE) for pose in sequence.poses[:FRAMES]]
    return {"K": torch.from_numpy(K), "poses": sequence.poses[:FRAMES],
            "rgb": [torch.from_numpy(rgb).permute(2, 0, 1) for rgb, _ in frames],
            "depth": [torch.from_numpy(depth)[None] for _, depth in frames]}


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Rotation (degrees) and translation (cm) error of one pose."""
    difference = np.linalg.inv(truth) @ estimate
    return float(rotation_angle_deg(difference[:3, :3])), float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


@pytest.mark.parametrize("gap", [1, 3])
def test_a_known_motion_is_recovered_from_a_start_a_frames_motion_off(rendered: dict, gap: int):
    truth = relative_pose(rendered["poses"][gap], rendered["poses"][0])  # T_frame_key, keyframe 0
    # about one frame's motion off: 0.3 degree and 1.3 mm
    nudge = pose_vec_to_matrix(torch.tensor([0.004, -0.003, 0.002, 0.08, -0.06, 0.08], dtype=torch.float64))
    start = nudge.numpy() @ truth
    result = align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][gap], rendered["K"],
                               torch.from_numpy(start), EXACT)
    rotation, translation = errors(result.T_frame_key.numpy(), truth)
    # from 0.3 degree and 0.13 cm; the rest is the renderer's light, which the fall-off model takes only in part
    assert rotation < 0.1 and translation < 0.01
    assert result.cost_end < 0.5 * result.cost_start
    assert result.gain == pytest.approx(1.0, abs=0.05) and result.offset == pytest.approx(0.0, abs=0.02)


@pytest.mark.parametrize("settings", [EXACT, AlignmentSettings()], ids=["light fall-off", "rotation prior"])
def test_trying_several_dampings_at_once_as_a_gpu_does_takes_the_step_one_at_a_time_would(
        rendered: dict, settings: AlignmentSettings, monkeypatch: pytest.MonkeyPatch):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    # far enough off that steps are refused and the damping climbs: 1.5 degrees and 0.5 cm
    nudge = pose_vec_to_matrix(torch.tensor([0.02, -0.015, 0.01, 0.3, -0.25, 0.3], dtype=torch.float64))
    judged = []  # (states compared, refused) of each comparison
    original = direct_alignment._compare
    monkeypatch.setattr(direct_alignment, "_compare", lambda *a: judged.append(
        (len(result := original(*a)), sum(after >= before for before, after, _ in result))) or result)

    def aligned(at_once: int) -> direct_alignment.Alignment:
        monkeypatch.setattr(direct_alignment, "candidates_at_once", lambda device: at_once)
        judged.clear()
        return align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3], rendered["K"],
                                 nudge @ torch.from_numpy(truth), settings)

    one = aligned(1)
    one_at_a_time = list(judged)
    three = aligned(3)
    assert sum(refused for _, refused in one_at_a_time) >= 3  # the damping climbed on the way
    assert max(states for states, _ in one_at_a_time) == 1 and max(states for states, _ in judged) == 3
    assert len(judged) < len(one_at_a_time)  # fewer waits for the device
    torch.testing.assert_close(three.T_frame_key, one.T_frame_key, rtol=0, atol=1e-6)
    assert three.cost_end == pytest.approx(one.cost_end, rel=1e-5) and three.valid_share == one.valid_share


def test_no_step_shorter_than_the_floor_is_tried_which_saves_evaluations_and_not_accuracy(
        rendered: dict, monkeypatch: pytest.MonkeyPatch):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    nudge = pose_vec_to_matrix(torch.tensor([0.004, -0.003, 0.002, 0.08, -0.06, 0.08], dtype=torch.float64))
    tried = []  # the largest component of each pose step tried
    original = direct_alignment.pose_vec_to_matrix
    monkeypatch.setattr(direct_alignment, "pose_vec_to_matrix",
                        lambda step: tried.append(float(step.abs().max())) or original(step))

    def aligned(floor: float) -> tuple[np.ndarray, int]:
        monkeypatch.setattr(direct_alignment, "MIN_STEP", floor)
        tried.clear()
        result = align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3], rendered["K"],
                                   nudge @ torch.from_numpy(truth), EXACT)
        assert min(tried) >= floor
        return result.T_frame_key.numpy(), len(tried)

    (floored, evaluations), (unfloored, every) = aligned(direct_alignment.MIN_STEP), aligned(0.0)
    assert min(tried) < 1e-7  # without the floor, steps shrink far below it before the damping gives up
    assert evaluations < 0.8 * every
    rotation, translation = errors(floored, unfloored)
    assert rotation < 1e-3 and translation < 1e-4  # degrees, cm: a hundredth of the error against the truth


def test_a_strong_rotation_prior_keeps_the_start_rotation_and_leaves_the_translation_to_the_frames(rendered: dict):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    turned = pose_vec_to_matrix(torch.tensor([0.003, -0.002, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)).numpy()
    start = turned @ truth
    start[:3, 3] = 0.5 * truth[:3, 3]  # half the true translation
    settings = {weight: replace(EXACT, rotation_prior=weight) for weight in (0.0, 0.1, 1e4)}
    result = {weight: align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3], rendered["K"],
                                        torch.from_numpy(start), value).T_frame_key.numpy()
              for weight, value in settings.items()}
    from_start = {weight: errors(pose, start)[0] for weight, pose in result.items()}
    from_truth = {weight: errors(pose, truth) for weight, pose in result.items()}
    assert from_start[1e4] < 0.002  # degrees: held at the start's rotation, 0.21 degree off the truth ...
    assert from_truth[1e4][1] < 0.2 * np.linalg.norm(truth[:3, 3])  # ... while the translation still comes
    assert from_truth[0.0][0] < 0.1  # free, the rotation goes to the truth (the rest: the renderer's light)
    assert from_start[1e4] < from_start[0.1] < from_start[0.0]  # in between, a weaker pull


def test_the_rotation_prior_measures_the_rotation_after_the_start_in_radians():
    start = pose_vec_to_matrix(torch.tensor([0.2, -0.1, 0.3, 1.0, 2.0, 3.0], dtype=torch.float64))
    theta = torch.tensor([0.01, 0.02, -0.005], dtype=torch.float64)
    pose = pose_vec_to_matrix(torch.cat([theta, torch.zeros(3, dtype=torch.float64)])) @ start
    prior = direct_alignment._RotationPrior(start[:3, :3], weight=2.0)
    torch.testing.assert_close(prior.departure(pose), theta)
    assert prior.cost(pose) == pytest.approx(0.5 * 2.0 * float(theta.square().sum()))
    assert prior.cost(start) == 0.0 and direct_alignment._RotationPrior(start[:3, :3], 0.0).cost(pose) == 0.0


def test_the_rotation_priors_gauss_newton_terms_are_the_derivatives_of_its_cost_over_the_pixels():
    start = pose_vec_to_matrix(torch.tensor([0.2, -0.1, 0.3, 1.0, 2.0, 3.0], dtype=torch.float64))
    prior, pixels, h = direct_alignment._RotationPrior(start[:3, :3], weight=0.3), 250, 1e-5
    basis = torch.eye(6, dtype=torch.float64)

    def total(pose: torch.Tensor, increment: torch.Tensor) -> float:  # over the pixels, after a left increment
        return pixels * prior.cost(pose_vec_to_matrix(increment) @ pose)

    moved = pose_vec_to_matrix(torch.tensor([0.004, -0.003, 0.002, 0.1, 0.0, 0.0], dtype=torch.float64)) @ start
    gradient = torch.tensor([(total(moved, h * e) - total(moved, -h * e)) / (2 * h) for e in basis])
    torch.testing.assert_close(prior.normal_equations(moved, pixels)[1], gradient.double(), rtol=1e-5, atol=1e-9)
    # the Hessian, exact at the start's rotation where the steps begin: the rotation block only
    hessian = torch.tensor([[(total(start, h * (a + b)) - total(start, h * (a - b)) - total(start, h * (b - a))
                              + total(start, -h * (a + b))) / (4 * h * h) for b in basis] for a in basis])
    torch.testing.assert_close(prior.normal_equations(start, pixels)[0], hessian.double(), rtol=1e-4, atol=1e-4)


def test_the_tracker_takes_every_refine_setting_from_the_params():
    cfg = RefineConfig(levels=2, max_size=128, iterations=5, huber=0.03, light_falloff=0.5, rotation_prior=0.3,
                       keyframe_every=4, min_overlap=0.4, rotation_smoothing=1.5)
    settings = tracker_settings(cfg)
    alignment = settings.alignment
    assert (alignment.levels, alignment.max_size, alignment.iterations, alignment.huber, alignment.light_falloff,
            alignment.rotation_prior) == (2, 128, 5, 0.03, 0.5, 0.3)
    assert (settings.keyframe_every, settings.min_overlap, settings.rotation_smoothing) == (4, 0.4, 1.5)


@pytest.mark.parametrize("size, max_size, halvings", [
    ((480, 480), None, 0), ((480, 480), 480, 0), ((480, 480), 479, 1), ((480, 480), 240, 1), ((480, 480), 239, 2),
    ((481, 481), 240, 1),  # a halving rounds down: 240
    ((1080, 1350), 256, 3), ((64, 64), 256, 0), ((32, 480), 64, 3),
    ((16, 480), 64, 2)])  # 4 px high, 120 wide: the shorter side is not halved below 4 px
def test_a_frame_is_halved_until_its_longer_side_fits_the_finest_level(size: tuple, max_size, halvings: int):
    assert direct_alignment.halvings_to_fit(*size, max_size) == halvings


def test_with_the_finest_level_at_half_the_frames_size_most_of_a_known_motion_is_recovered(rendered: dict):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    nudge = pose_vec_to_matrix(torch.tensor([0.004, -0.003, 0.002, 0.08, -0.06, 0.08], dtype=torch.float64))
    error = {max_size: errors(align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3],
                                                rendered["K"], nudge @ torch.from_numpy(truth),
                                                replace(EXACT, max_size=max_size)).T_frame_key.numpy(), truth)
             for max_size in (None, SIZE // 2)}
    rotation, translation = error[SIZE // 2]
    assert rotation < 0.75 * 0.31 and translation < 0.2 * 0.128  # of the start's 0.31 degree and 0.128 cm
    assert rotation > error[None][0] and translation > error[None][1]  # a quarter of the pixels: less exact


def test_a_capped_pyramid_is_the_full_pyramids_coarser_levels(rendered: dict):
    arguments = (rendered["rgb"][0].float(), rendered["depth"][0].float(), rendered["rgb"][3].float(),
                 rendered["K"].float())
    full = direct_alignment._pyramid(*arguments, levels=3)
    capped = direct_alignment._pyramid(*arguments, levels=2, max_size=SIZE // 2)
    assert len(capped) == 2
    for ours, theirs in zip(capped, full[1:]):
        for field in ("key_rgb", "points", "usable", "frame", "gradients", "K"):
            assert torch.equal(getattr(ours, field), getattr(theirs, field)), field


def test_a_change_of_brightness_is_taken_up_by_the_gain_and_offset(rendered: dict):
    truth = relative_pose(rendered["poses"][2], rendered["poses"][0])
    brighter = (rendered["rgb"][2] * 1.2 + 0.03).clamp(0, 1)  # the light moves with the camera
    result = align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], brighter, rendered["K"],
                               torch.eye(4, dtype=torch.float64), EXACT)
    rotation, translation = errors(result.T_frame_key.numpy(), truth)
    assert rotation < 0.1 and translation < 0.1 * np.linalg.norm(truth[:3, 3])
    # frame = key / 1.2 - 0.025 in the key's terms
    assert result.gain == pytest.approx(1 / 1.2, rel=0.03) and result.offset == pytest.approx(-0.03 / 1.2, abs=0.01)


def test_a_black_field_of_view_border_does_not_hold_the_camera_still(rendered: dict, monkeypatch):
    """The border is black in every frame at the same place: taken as scene, it says the camera did not move."""
    v, u = np.mgrid[:SIZE, :SIZE]
    inside = torch.from_numpy(((u - 31.5) ** 2 + (v - 31.5) ** 2 <= 30.0**2).astype(np.float64))
    key, frame = rendered["rgb"][0] * inside, rendered["rgb"][3] * inside
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    motion = np.linalg.norm(truth[:3, 3])

    def translation_error() -> float:
        result = align_to_keyframe(key, rendered["depth"][0], frame, rendered["K"], torch.eye(4, dtype=torch.float64),
                                   EXACT)
        return errors(result.T_frame_key.numpy(), truth)[1]

    assert translation_error() < 0.1 * motion
    monkeypatch.setattr(direct_alignment, "BLACK", -1.0)  # black pixels taken as scene
    assert translation_error() > 0.5 * motion


def test_tracking_a_sequence_follows_the_camera_where_constant_velocity_cannot(rendered: dict):
    poses = rendered["poses"]
    steps = relative_pose(poses[:-1], poses[1:])
    constant = mean_step(steps)  # the sequence's own mean step: the best any constant step can do
    tracker = KeyframeTracker(rendered["K"], TrackerSettings(EXACT, keyframe_every=6))
    tracked = [tracker.track(rendered["rgb"][0], rendered["depth"][0], torch.from_numpy(poses[0]))]
    for rgb, depth in zip(rendered["rgb"][1:], rendered["depth"][1:]):
        tracked.append(tracker.track(rgb, depth, tracked[-1] @ torch.from_numpy(constant)))
    tracked_steps = relative_pose(*(lambda p: (p[:-1], p[1:]))(torch.stack(tracked).numpy()))
    ours = metrics.simcol_pose_sequence(poses, tracked_steps)
    start = metrics.simcol_pose_sequence(poses, np.repeat(constant[None], len(steps), axis=0))
    assert ours["rte"] < 0.25 * start["rte"]
    assert ours["scale"] == pytest.approx(1.0, abs=0.05)  # exact depth: the path comes out in cm
    assert metrics.motion_agreement(poses, tracked_steps)["step_corr"] > 0.9


def test_the_tracked_pose_is_rigid_whatever_the_start(rendered: dict):
    """A start whose rotation block has shrunk (a long chain of float32 steps) gives a rigid pose: chained through
    keyframes, a shrinking rotation would otherwise reach a singular matrix."""
    tracker = KeyframeTracker(rendered["K"], TrackerSettings(EXACT, keyframe_every=2))
    pose = torch.from_numpy(rendered["poses"][0])
    for rgb, depth in zip(rendered["rgb"][:6], rendered["depth"][:6]):
        start = pose.clone()
        start[:3, :3] *= 0.95
        pose = tracker.track(rgb, depth, start)
        rotation = pose[:3, :3]
        torch.testing.assert_close(rotation @ rotation.T, torch.eye(3, dtype=rotation.dtype), rtol=0, atol=1e-9)
        assert torch.equal(pose[3], torch.tensor([0, 0, 0, 1], dtype=pose.dtype))


def test_modelling_the_lights_fall_off_takes_out_most_of_the_rotation_bias_with_exact_depth(rendered: dict):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    error = {falloff: errors(align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3],
                                               rendered["K"], torch.from_numpy(truth),
                                               replace(EXACT, light_falloff=falloff)).T_frame_key.numpy(), truth)[0]
             for falloff in (0.0, 0.91)}
    assert error[0.91] < 0.5 * error[0.0]


def _level_and_states(rendered: dict, settings: AlignmentSettings, compiled: bool, odd_camera: bool = False
                      ) -> tuple:
    """The finest level of frames 0 and 3 and three states around the truth (as ``_costs`` takes them); with an
    ``odd_camera``, the frames cropped to 64 x 40 off centre, K skewed, a black corner and a highlight in both
    (every term of K and of the exposure test then counts)."""
    key, frame, depth, K = (rendered["rgb"][0].float(), rendered["rgb"][3].float(), rendered["depth"][0].float(),
                            rendered["K"].float())
    if odd_camera:
        key, frame, depth = (image[:, 6:46].clone() for image in (key, frame, depth))
        K = K.clone()
        K[1, 2] -= 6  # the crop's principal point
        K[0, 1] = 0.8  # a skew: the tests compare the two codes, not the geometry
        for image in (key, frame):
            image[:, :10, :12] = 0  # black, as outside a field of view
            image[:, 20:24, 30:36] = 1  # saturated, as a highlight
    level = direct_alignment._pyramid(key, depth, frame, K, levels=1, compiled=compiled)[0]
    truth = torch.from_numpy(relative_pose(rendered["poses"][3], rendered["poses"][0]))
    nudges = torch.tensor([[0.0] * 6, [0.004, -0.003, 0.002, 0.08, -0.06, 0.08], [-0.01, 0.0, 0.01, 0.0, 0.2, 0.0]],
                          dtype=torch.float64)
    poses = torch.stack([pose_vec_to_matrix(nudge) @ truth for nudge in nudges])
    brightness = torch.tensor([[0.0, 0.0], [0.1, -0.02], [-0.05, 0.01]], dtype=torch.float64)
    prior = direct_alignment._RotationPrior(truth[:3, :3], settings.rotation_prior)
    return level, poses, brightness, prior


@pytest.mark.parametrize("settings, odd_camera", [
    (EXACT, False), (AlignmentSettings(huber=0.01), False), (EXACT, True)],
    ids=["light fall-off", "no fall-off, rotation prior, huber 0.01", "light fall-off, odd camera"])
def test_the_compiled_loops_cost_and_linearise_a_state_as_the_tensor_code_does(rendered: dict,
                                                                              settings: AlignmentSettings,
                                                                              odd_camera: bool):
    """To float32 rounding: the loops sample at the pixel directly, the tensor code through grid_sample's grid."""
    loops, tensors = (_level_and_states(rendered, settings, compiled, odd_camera) for compiled in (True, False))
    assert loops[0].compiled and not tensors[0].compiled
    (cost_loops, part_loops, at_loops), (cost_tensors, part_tensors, at_tensors) = (
        direct_alignment._costs(level, poses, brightness, settings, prior)
        for level, poses, brightness, prior in (loops, tensors))
    both = part_loops & part_tensors
    assert (part_loops != part_tensors).sum() <= 3 and both.sum() > 0.5 * both[0].numel()  # a point on an edge
    torch.testing.assert_close(cost_loops[both], cost_tensors[both], rtol=1e-4, atol=1e-7)
    assert not cost_loops[~part_loops].any()  # a point that does not take part costs nothing
    for index in range(3):
        (normal_loops, count_loops), (normal_tensors, count_tensors) = (
            direct_alignment._normal_equations(level, at.pick(index), brightness[index], settings)
            for (level, _, brightness, _), at in ((loops, at_loops), (tensors, at_tensors)))
        assert count_loops == int(part_loops[index].sum()) and abs(count_loops - count_tensors) <= 3
        assert normal_loops.dtype == torch.float64 and normal_loops.shape == (8, 9)
        # the Hessian symmetric to float32 rounding (the rows' products are summed in float32, in an order that the
        # matrix product's blocking sets and that can differ between an entry and its mirror: 2e-5 of it apart on an
        # AVX2 CPU), and each entry the tensor code's, both to a ten-thousandth of the largest in its row
        hessian = normal_loops[:, :8]
        assert ((hessian - hessian.T).abs() <= 1e-4 * hessian.abs().amax(dim=1, keepdim=True)).all()
        scale = normal_tensors.abs().amax(dim=1, keepdim=True)
        assert ((normal_loops - normal_tensors).abs() <= 1e-4 * scale).all()


def test_the_compiled_loops_align_a_frame_as_the_tensor_code_does(rendered: dict):
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    nudge = pose_vec_to_matrix(torch.tensor([0.004, -0.003, 0.002, 0.08, -0.06, 0.08], dtype=torch.float64))
    for settings in (EXACT, AlignmentSettings()):
        loops, tensors = (align_to_keyframe(rendered["rgb"][0], rendered["depth"][0], rendered["rgb"][3],
                                            rendered["K"], nudge @ torch.from_numpy(truth),
                                            replace(settings, compiled=compiled)) for compiled in (True, False))
        torch.testing.assert_close(loops.T_frame_key, tensors.T_frame_key, rtol=0, atol=1e-6)
        assert loops.cost_end == pytest.approx(tensors.cost_end, rel=1e-4)
        assert loops.valid_share == pytest.approx(tensors.valid_share, abs=1e-3)


def test_where_no_pixel_takes_part_the_compiled_normal_equations_are_empty(rendered: dict):
    level, poses, brightness, _ = _level_and_states(rendered, EXACT, compiled=True)
    behind = poses[0].clone()
    behind[2, 3] -= 1e3  # the scene 10 m behind the camera
    states = torch.cat([behind[:3].reshape(1, 12), torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)], dim=1)
    normal, count = alignment_loops.normal_equations(level.loop_arrays(0.0), states[0].float().numpy(), 0.1, 0.0)
    assert count == 0 and torch.equal(normal, torch.zeros(8, 9, dtype=torch.float64))


def test_frames_and_depth_that_carry_gradients_are_aligned_as_any_others(rendered: dict):
    """The alignment reads the tensors' values: a caller's autograd graph is neither needed nor followed."""
    truth = relative_pose(rendered["poses"][3], rendered["poses"][0])
    arguments = [rendered["rgb"][0], rendered["depth"][0].float(), rendered["rgb"][3], rendered["K"]]
    plain = align_to_keyframe(*arguments, torch.from_numpy(truth), EXACT)
    tracked = align_to_keyframe(*(tensor.clone().requires_grad_() for tensor in arguments), torch.from_numpy(truth),
                                EXACT)
    assert torch.equal(tracked.T_frame_key, plain.T_frame_key) and not tracked.T_frame_key.requires_grad


def _tracked_with_drifting_depth(rendered: dict, depth_scale: bool) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """S5 tracked from constant velocity with exact depth whose scale drifts from 1 at the first frame to 1.5 at the
    last (as the model's does on the real C3VD sample): the true and tracked paths and the tracker's factors."""
    poses = rendered["poses"]
    drift = np.linspace(1.0, 1.5, len(poses))
    constant = torch.from_numpy(mean_step(relative_pose(poses[:-1], poses[1:])))
    tracker = KeyframeTracker(rendered["K"], TrackerSettings(EXACT, depth_scale=depth_scale))
    tracked, factors = [], []
    for rgb, depth, wrong in zip(rendered["rgb"], rendered["depth"], drift):
        start = torch.from_numpy(poses[0]) if not tracked else tracked[-1] @ constant
        tracked.append(tracker.track(rgb, depth * float(wrong), start))
        factors.append(tracker.depth_scale * wrong)  # 1 where the rescaled depth is the true one
    return poses, torch.stack(tracked).numpy(), factors


def test_rescaling_each_frames_depth_to_its_keyframes_undoes_a_drift_of_the_depths_scale(rendered: dict):
    poses, tracked, factors = _tracked_with_drifting_depth(rendered, depth_scale=True)
    assert factors[0] == 1.0 and max(abs(f - 1) for f in factors) < 0.01
    steps = relative_pose(tracked[:-1], tracked[1:])
    assert metrics.simcol_pose_sequence(poses, steps)["scale"] == pytest.approx(1.0, abs=0.03)
    # without it the path takes each keyframe's scale: its steps grow with the drift
    poses, tracked, factors = _tracked_with_drifting_depth(rendered, depth_scale=False)
    assert factors[-1] == pytest.approx(1.5)
    lengths = np.linalg.norm(relative_pose(tracked[:-1], tracked[1:])[:, :3, 3], axis=1)
    true = np.linalg.norm(relative_pose(poses[:-1], poses[1:])[:, :3, 3], axis=1)
    assert np.median((lengths / true)[-10:]) > 1.3 * np.median((lengths / true)[:10])
