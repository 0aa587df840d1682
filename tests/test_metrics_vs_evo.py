"""Our trajectory metrics are evo's metrics given the same alignment.

``endoflow.evaluation.metrics`` keeps its own pose metrics (the SimCol3D challenge's and EndoSLAM's protocols);
this module checks them against evo (``evo.core.metrics``) on the same trajectories, to 1e-9 relative:

- SimCol3D (``simcol_pose_sequence``): given the GT poses and our returned ``trajectory`` (our prediction,
  already scaled and chained from ``P_0`` by the protocol), evo's RPE over consecutive frames (``delta`` 1 frame)
  per pair is our per-frame ``rte`` (``translation_part``) and ``rot`` (``rotation_angle_deg``), and evo's APE
  ``translation_part`` with no alignment per pose is our per-frame ``ate``; the three medians are evo's medians.
- EndoSLAM (``endoslam_pose_sequence``): with the GT expressed relative to ``P_0`` and our prediction chained
  from the identity with our scale, our ``ate`` is evo's APE ``translation_part`` RMSE and our ``rpe_trans`` /
  ``rpe_rot`` are the means of evo's consecutive RPE ``translation_part`` / ``rotation_angle_deg``.
- Alignment done by evo: ``est.scale(s)`` on the prediction chained from the identity, then
  ``est.align_origin(gt)``, gives our EndoSLAM figures in world coordinates, where ``s`` is OUR scale.
- Our scales are optima of evo's errors: the SimCol3D scale minimises the RMSE of evo's consecutive RPE
  ``translation_part`` on the chained path, the EndoSLAM scale the RMSE of evo's APE after ``scale`` and
  ``align_origin``.

How our alignment differs from evo's own (what a user of evo must do to reproduce our numbers):

- evo's scale correction (``evo_ape -s``, ``PosePath3D.align(..., correct_only_scale=True)``) takes the scale
  of an Umeyama Sim(3) fit: positions centred on their means and a rotation fitted too (the scale is
  ``trace(D S) / var(est)``), of which only the scale is applied, about the world origin. Ours is the plain
  least-squares ``s = sum <g_i, p_i> / sum |p_i|^2`` of positions relative to ``P_0`` in ``P_0``'s camera
  frame: no centring, no rotation, the scaling about the first pose. ``evo_ape -s --align_origin`` (evo scales,
  then moves the first pose onto the reference's) has our protocol's form, scaling about the first pose, but
  evo's scale value. The two scales agree when the prediction is the GT up to scale and differ as soon as it
  has noise, so evo's scale correction is not our protocol: give evo our scale (``PosePath3D.scale``) and
  ``align_origin``, as the tests below do.
- The SimCol3D challenge fits its scale on RELATIVE translations (each in its frame ``i``), then chains; evo has
  no such fit. Its RTE/ROT/ATE are evo's RPE/APE only once the trajectory is chained with that scale.
- evo labels translation errors in metres but never converts unless asked (``change_unit``): cm in, cm out.
- Rotation angles: ours is ``arccos((trace - 1) / 2)``, evo's the norm of scipy's rotation vector; the same
  number, but arccos loses precision for small angles (about ``2e-16 / angle`` rad absolute, ``2e-16 / angle^2``
  relative), so the 1e-9 agreement asserted here holds for errors above about 0.03 degree (these paths' smallest
  is 0.07 degree); below it the two still agree to far less than any reported digit.
"""

from __future__ import annotations

import numpy as np
import pytest
from evo.core.metrics import APE, RPE, PoseRelation, StatisticsType, Unit
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from endoflow.evaluation import metrics

RTOL = 1e-9
FPS = 30.0
NETWORK_SCALE = 0.37  # a model's depth and path come in its own units: cm times an unknown factor


# ------------------------------------------------------------------------------------------ trajectories
def smooth_camera_path(count: int, rng: np.random.Generator) -> np.ndarray:
    """``[count, 4, 4]`` camera-to-world poses of a camera advancing about 0.4 cm per frame through a winding
    tube, turning and rolling slowly: an endoscope's path, with seeded shape."""
    t = np.arange(count, dtype=np.float64)
    phase = rng.uniform(0.0, 2 * np.pi, size=5)
    amplitude = rng.uniform(1.0, 3.0, size=2)
    positions = np.stack([amplitude[0] * np.sin(0.15 * t + phase[0]),
                          amplitude[1] * np.cos(0.11 * t + phase[1]),
                          0.4 * t], axis=1) + rng.normal(scale=10.0, size=3)
    rotvecs = np.stack([0.3 * np.sin(0.08 * t + phase[2]), 0.3 * np.sin(0.06 * t + phase[3]),
                        0.02 * t + phase[4]], axis=1)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    poses[:, :3, 3] = positions
    return poses


def noisy_prediction(gt_poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A model's ``(N-1)`` relative poses ``Q'_i``: the GT motion with about half a degree and half a millimetre
    of noise per frame, in the network's scale."""
    relative = metrics.relative_poses(gt_poses)
    noise = Rotation.from_rotvec(rng.normal(scale=np.radians(0.5), size=(len(relative), 3))).as_matrix()
    relative[:, :3, :3] = noise @ relative[:, :3, :3]
    relative[:, :3, 3] = (relative[:, :3, 3] + rng.normal(scale=0.05, size=(len(relative), 3))) * NETWORK_SCALE
    return relative


def exact_up_to_scale(gt_poses: np.ndarray) -> np.ndarray:
    """The GT relative poses with every translation in the network's scale: a perfect model."""
    return metrics.scaled_relative_poses(metrics.relative_poses(gt_poses), NETWORK_SCALE)


def evo_trajectory(poses: np.ndarray) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.arange(len(poses)) / FPS)


def case(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """GT poses and a noisy prediction, 30 to 50 frames."""
    rng = np.random.default_rng(seed)
    gt_poses = smooth_camera_path(int(rng.integers(30, 51)), rng)
    return gt_poses, noisy_prediction(gt_poses, rng)


def evo_errors(metric: APE | RPE, reference: PoseTrajectory3D, estimate: PoseTrajectory3D) -> np.ndarray:
    metric.process_data((reference, estimate))
    return metric.error


def consecutive_rpe(relation: PoseRelation) -> RPE:
    return RPE(relation, delta=1, delta_unit=Unit.frames, all_pairs=False)


SEEDS = [0, 1, 2]


# --------------------------------------------------------------------------------------------- SimCol3D
@pytest.mark.parametrize("seed", SEEDS)
def test_simcol_per_pair_rte_and_rot_are_evos_consecutive_rpe_on_our_scaled_trajectory(seed: int):
    gt_poses, predicted = case(seed)
    ours = metrics.simcol_pose_sequence(gt_poses, predicted)
    reference, estimate = evo_trajectory(gt_poses), evo_trajectory(ours["trajectory"])
    rte = consecutive_rpe(PoseRelation.translation_part)
    rot = consecutive_rpe(PoseRelation.rotation_angle_deg)
    np.testing.assert_allclose(ours["per_frame"]["rte"], evo_errors(rte, reference, estimate), rtol=RTOL)
    np.testing.assert_allclose(ours["per_frame"]["rot"], evo_errors(rot, reference, estimate), rtol=RTOL)
    assert ours["rte"] == pytest.approx(rte.get_statistic(StatisticsType.median), rel=RTOL)
    assert ours["rot"] == pytest.approx(rot.get_statistic(StatisticsType.median), rel=RTOL)


@pytest.mark.parametrize("seed", SEEDS)
def test_simcol_per_pose_ate_local_is_evos_unaligned_ape_on_our_scaled_trajectory(seed: int):
    gt_poses, predicted = case(seed)
    ours = metrics.simcol_pose_sequence(gt_poses, predicted)
    ape = APE(PoseRelation.translation_part)
    evo_ate = evo_errors(ape, evo_trajectory(gt_poses), evo_trajectory(ours["trajectory"]))
    assert evo_ate[0] == 0.0  # both start at P_0: the protocol aligns the origin, evo need not
    np.testing.assert_allclose(ours["per_frame"]["ate_local"], evo_ate, rtol=RTOL)
    assert ours["ate_local"] == pytest.approx(ape.get_statistic(StatisticsType.median), rel=RTOL)


def rpe_translation_rmse_at_scale(gt_poses: np.ndarray, predicted: np.ndarray, scale: float) -> float:
    chained = metrics.chain_relative_poses(gt_poses[0], metrics.scaled_relative_poses(predicted, scale))
    rpe = consecutive_rpe(PoseRelation.translation_part)
    rpe.process_data((evo_trajectory(gt_poses), evo_trajectory(chained)))
    return rpe.get_statistic(StatisticsType.rmse)


@pytest.mark.parametrize("seed", SEEDS)
def test_simcol_scale_is_the_one_that_minimises_evos_consecutive_rpe_translation_rmse(seed: int):
    """``|t(E_i)| = |s t(Q'_i) - t(Q_i)|`` (a rotation keeps lengths): the least-squares fit on relative
    translations is the scale of least RPE, which evo can check but not fit."""
    gt_poses, predicted = case(seed)
    scale = metrics.simcol_pose_sequence(gt_poses, predicted)["scale"]
    best = rpe_translation_rmse_at_scale(gt_poses, predicted, scale)
    assert all(best < rpe_translation_rmse_at_scale(gt_poses, predicted, scale * factor) for factor in (0.99, 1.01))


def test_simcol_scale_undoes_the_network_scale_of_an_exact_prediction():
    gt_poses = smooth_camera_path(40, np.random.default_rng(3))
    ours = metrics.simcol_pose_sequence(gt_poses, exact_up_to_scale(gt_poses))
    assert ours["scale"] == pytest.approx(1 / NETWORK_SCALE, rel=RTOL)
    ape = APE(PoseRelation.translation_part)
    assert evo_errors(ape, evo_trajectory(gt_poses), evo_trajectory(ours["trajectory"])).max() < 1e-9


# --------------------------------------------------------------------------------------------- EndoSLAM
def endoslam_pair_for_evo(gt_poses: np.ndarray, predicted: np.ndarray, scale: float
                          ) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """The protocol's frame: GT relative to ``P_0``, the prediction chained from the identity with ``scale``."""
    gt_local = np.linalg.inv(gt_poses[0]) @ gt_poses
    estimate = metrics.chain_relative_poses(np.eye(4), metrics.scaled_relative_poses(predicted, scale))
    return evo_trajectory(gt_local), evo_trajectory(estimate)


@pytest.mark.parametrize("seed", SEEDS)
def test_endoslam_ate_and_rpe_means_are_evos_on_the_protocols_frame(seed: int):
    gt_poses, predicted = case(seed)
    ours = metrics.endoslam_pose_sequence(gt_poses, predicted)
    reference, estimate = endoslam_pair_for_evo(gt_poses, predicted, ours["scale"])
    ape = APE(PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    rpe_trans = consecutive_rpe(PoseRelation.translation_part)
    rpe_trans.process_data((reference, estimate))
    rpe_rot = consecutive_rpe(PoseRelation.rotation_angle_deg)
    rpe_rot.process_data((reference, estimate))
    assert ours["ate"] == pytest.approx(ape.get_statistic(StatisticsType.rmse), rel=RTOL)
    assert ours["rpe_trans"] == pytest.approx(rpe_trans.get_statistic(StatisticsType.mean), rel=RTOL)
    assert ours["rpe_rot"] == pytest.approx(rpe_rot.get_statistic(StatisticsType.mean), rel=RTOL)


@pytest.mark.parametrize("seed", SEEDS)
def test_evos_origin_alignment_with_our_scale_gives_our_endoslam_figures_in_world_coordinates(seed: int):
    gt_poses, predicted = case(seed)
    ours = metrics.endoslam_pose_sequence(gt_poses, predicted)
    reference = evo_trajectory(gt_poses)
    estimate = evo_trajectory(metrics.chain_relative_poses(np.eye(4), predicted))
    estimate.scale(ours["scale"])  # about the world origin, where the chain starts: about the first pose
    estimate.align_origin(reference)
    ape = APE(PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    rpe_trans = consecutive_rpe(PoseRelation.translation_part)
    rpe_trans.process_data((reference, estimate))
    rpe_rot = consecutive_rpe(PoseRelation.rotation_angle_deg)
    rpe_rot.process_data((reference, estimate))
    assert ours["ate"] == pytest.approx(ape.get_statistic(StatisticsType.rmse), rel=RTOL)
    assert ours["rpe_trans"] == pytest.approx(rpe_trans.get_statistic(StatisticsType.mean), rel=RTOL)
    assert ours["rpe_rot"] == pytest.approx(rpe_rot.get_statistic(StatisticsType.mean), rel=RTOL)


def origin_aligned_ape_rmse_at_scale(gt_poses: np.ndarray, predicted: np.ndarray, scale: float) -> float:
    reference = evo_trajectory(gt_poses)
    estimate = evo_trajectory(metrics.chain_relative_poses(np.eye(4), predicted))
    estimate.scale(scale)
    estimate.align_origin(reference)
    ape = APE(PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    return ape.get_statistic(StatisticsType.rmse)


@pytest.mark.parametrize("seed", SEEDS)
def test_endoslam_scale_is_the_one_that_minimises_evos_origin_aligned_ape_rmse(seed: int):
    gt_poses, predicted = case(seed)
    scale = metrics.endoslam_pose_sequence(gt_poses, predicted)["scale"]
    best = origin_aligned_ape_rmse_at_scale(gt_poses, predicted, scale)
    assert all(best < origin_aligned_ape_rmse_at_scale(gt_poses, predicted, scale * factor) for factor in (0.99, 1.01))


def evos_only_scale(gt_poses: np.ndarray, predicted: np.ndarray) -> float:
    """The scale evo's ``correct_only_scale`` finds for the prediction, both paths in ``P_0``'s frame."""
    reference, estimate = endoslam_pair_for_evo(gt_poses, predicted, 1.0)
    return float(estimate.align(reference, correct_only_scale=True)[2])


def test_evos_scale_correction_is_ours_for_an_exact_prediction_up_to_scale():
    gt_poses = smooth_camera_path(40, np.random.default_rng(4))
    predicted = exact_up_to_scale(gt_poses)
    ours = metrics.endoslam_pose_sequence(gt_poses, predicted)
    assert ours["scale"] == pytest.approx(1 / NETWORK_SCALE, rel=RTOL)
    assert evos_only_scale(gt_poses, predicted) == pytest.approx(ours["scale"], rel=RTOL)


@pytest.mark.parametrize("seed", SEEDS)
def test_evos_scale_correction_is_not_ours_for_a_noisy_prediction(seed: int):
    """Umeyama's scale (centred positions, a fitted rotation) is not our least-squares scale about ``P_0``:
    with half a degree of noise per frame they part by 0.2 to 1 %, so evo must be given our scale."""
    gt_poses, predicted = case(seed)
    ours = metrics.endoslam_pose_sequence(gt_poses, predicted)["scale"]
    assert abs(evos_only_scale(gt_poses, predicted) / ours - 1.0) > 1e-3
