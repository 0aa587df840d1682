"""Depth and pose error metrics, in the protocols the literature reports (pure numpy).

Three protocols, each labelled in every output so tables never mix them:

- ``paper``: the Monodepth2-style protocol of the paper's released code. Per image: keep ``gt > 0``,
  median-scale the prediction (``median(gt) / median(pred)``), clamp it to ``[1e-3, 20]`` cm, then Abs Rel,
  Sq Rel, RMSE, RMSE log, L1 and the three ``delta < 1.25^k`` accuracies; averaged over images, as is the
  scale the median scaling applied (``ratio``: 1 where the prediction is metric). Beside them (ours), the depth's
  shape: ``near_ratio`` and ``far_ratio``, the median of GT over the scaled prediction among the GT's nearest and
  farthest tenth of pixels (1 where near and far keep their proportion; above 1 at the far end: the far depth is
  compressed, as auto-masking leaves it, docs/results.md).
- ``simcol``: the SimCol3D challenge's evaluation scripts. Depth: predictions are ``depth / 20`` clipped to
  ``[0, 1]``, ONE least-squares scale per sequence from per-image means, then per image L1 (cm), median
  relative error (%, the per-image median, so the sequence figure is a mean of medians) and RMSE (cm),
  averaged over the sequence's images; no mask, no cap. Pose: relative GT poses ``Q_i = inv(P_i) @ P_{i+1}``,
  a scale ``s`` fitted on relative translations, ``E_i = inv(Q_i) @ Q'_i`` with the translation of ``Q'_i``
  scaled; medians of ``|t(E_i)|`` (RTE, cm) and of the rotation angle of ``E_i`` (ROT, degrees). ATE (cm),
  exactly as the challenge script computes it: the unscaled ``Q'_i`` chained from ``P_0``, then every
  absolute position of the chain multiplied by ``s``, the median of ``|t(P_i) - s t(P'_i)|``; ``P_0``'s
  distance from the world origin is scaled too, so this figure depends on where the origin is.
  ``ate_local`` (ours, beside it): the scaled ``Q'_i`` chained from ``P_0``, the median of
  ``|t(P_i) - t(P'_i)|``, the same wherever the origin is.
- ``endoslam``: KITTI-odometry-style figures as EndoSLAM reports them: ATE as the RMSE of positions after a
  least-squares scale alignment of the trajectory (both starting at the first GT pose), RPE as the mean
  translation (cm) and rotation (degrees) error of consecutive relative poses.
- ``motion`` (ours): whether a predicted path follows the camera's changes of motion, which RTE and ROT cannot
  tell where the true motion barely changes: the Pearson correlation over a sequence's steps of the predicted
  and true step length, signed forward component and rotation angle (0 where either side is constant: a
  constant step follows none of the changes), the spread of the predicted step lengths (after the challenge's
  scale) over the true ones, and the median angle between predicted and true translation directions (the
  error two-view methods make apart from rotation).
- ``scale`` (ours): whether depth and path share one scale, which a map needs (a length measured in it is wrong by
  their ratio): ``path_over_depth``, the challenge's translation scale of the path over the median of the paper
  protocol's per-frame depth scaling (1 when they agree), and ``depth_drift``, the median depth scaling of the
  sequence's last quarter over its first quarter (1 when the depth keeps its scale along the sequence).

Conventions: depth maps are z-depth in cm, ``H x W`` (or ``N x H x W``); poses are ``4 x 4`` camera-to-world
``T_world_cam``; a relative pose ``Q_i = inv(P_i) @ P_{i+1}`` maps points in frame ``i+1`` into frame ``i``.
"""

from __future__ import annotations

import numpy as np

from endoflow.geometry.pose import rotation_angle_deg
from endoflow.shapes import check_shape

PAPER_MIN_DEPTH_CM = 1e-3
PAPER_MAX_DEPTH_CM = 20.0
SIMCOL_DEPTH_RANGE_CM = 20.0  # challenge predictions are depth / 20 cm in [0, 1]
SIMCOL_REL_EPS_CM = 1e-4  # the challenge code's 10e-5 added to the GT in the relative error

PAPER_DEPTH_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "l1", "a1", "a2", "a3", "ratio", "near_ratio", "far_ratio")
SHAPE_SHARE = 0.1  # the nearest and farthest tenth of an image's GT pixels: the depth's shape figures
SIMCOL_DEPTH_KEYS = ("l1", "rel", "rmse")
SIMCOL_POSE_KEYS = ("ate", "ate_local", "rte", "rot")
ENDOSLAM_POSE_KEYS = ("ate", "rpe_trans", "rpe_rot")
MOTION_KEYS = ("step_corr", "forward_corr", "rotation_corr", "step_spread", "direction_deg")
SCALE_KEYS = ("path_over_depth", "depth_drift")
# a step shorter than this share of the sequence's median true step has no direction to find (a pausing camera)
DIRECTION_MIN_STEP_SHARE = 0.1


# ------------------------------------------------------------------------------------------ depth
def paper_depth_errors(gt_cm: np.ndarray, pred_cm: np.ndarray) -> dict[str, float]:
    """Paper-protocol errors of ONE image (median scaling inside).

    Args:
        gt_cm: ``H x W`` GT z-depth in cm, ``0`` where unknown.
        pred_cm: ``H x W`` predicted depth (any positive scale), same size as ``gt_cm``.

    Returns:
        ``abs_rel, sq_rel, rmse, rmse_log, l1, a1, a2, a3``, the applied ``ratio`` and the shape figures
        ``near_ratio, far_ratio`` (:func:`shape_ratios`).
    """
    gt_cm, pred_cm = _same_shape_2d("gt_cm", gt_cm, "pred_cm", pred_cm)
    mask = gt_cm > 0
    if not mask.any():
        raise ValueError("paper depth protocol: the GT depth map has no valid (> 0) pixel")
    gt = gt_cm[mask].astype(np.float64)
    pred = pred_cm[mask].astype(np.float64)
    ratio = float(np.median(gt) / np.median(pred))
    pred = np.clip(pred * ratio, PAPER_MIN_DEPTH_CM, PAPER_MAX_DEPTH_CM)
    thresh = np.maximum(gt / pred, pred / gt)
    return {
        "abs_rel": float(np.mean(np.abs(gt - pred) / gt)),
        "sq_rel": float(np.mean((gt - pred) ** 2 / gt)),
        "rmse": float(np.sqrt(np.mean((gt - pred) ** 2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "l1": float(np.mean(np.abs(gt - pred))),
        "a1": float(np.mean(thresh < 1.25)),
        "a2": float(np.mean(thresh < 1.25**2)),
        "a3": float(np.mean(thresh < 1.25**3)),
        "ratio": ratio,
        **shape_ratios(gt, pred),
    }


def shape_ratios(gt: np.ndarray, pred: np.ndarray) -> dict[str, float]:
    """``near_ratio`` and ``far_ratio``: the median of ``gt / pred`` over the pixels at or below the GT's
    :data:`SHAPE_SHARE` quantile and at or above its ``1 - SHAPE_SHARE`` quantile (flat arrays of known pixels, the
    prediction already scaled and clamped). Pixels tied at a quantile all join its share: a GT saturated at its far
    end counts whole, and a GT of one depth gives both shares every pixel."""
    near, far = np.quantile(gt, [SHAPE_SHARE, 1 - SHAPE_SHARE])
    return {"near_ratio": float(np.median(gt[gt <= near] / pred[gt <= near])),
            "far_ratio": float(np.median(gt[gt >= far] / pred[gt >= far]))}


def depth_to_simcol_unit(depth_cm: np.ndarray) -> np.ndarray:
    """Depth in cm to the challenge's prediction encoding: ``depth / 20`` clipped to ``[0, 1]``."""
    return np.clip(np.asarray(depth_cm, dtype=np.float64) / SIMCOL_DEPTH_RANGE_CM, 0.0, 1.0)


def simcol_depth_scale(pred_unit: np.ndarray, gt_cm: np.ndarray) -> float:
    """The challenge's per-sequence scale ``sum(mean(p_k) mean(g_k)) / sum(mean(p_k)^2)``, in unit-space.

    Args:
        pred_unit: ``N x H x W`` predictions in ``[0, 1]`` (depth / 20 cm), already clipped.
        gt_cm: ``N x H x W`` GT depth in cm.
    """
    pred_means = _image_means(pred_unit, "pred_unit")
    gt_means = _image_means(np.asarray(gt_cm, dtype=np.float64) / SIMCOL_DEPTH_RANGE_CM, "gt_cm")
    denominator = float(np.sum(pred_means * pred_means))
    if denominator <= 0:
        raise ValueError("SimCol3D depth protocol: every prediction of the sequence is zero")
    return float(np.sum(pred_means * gt_means) / denominator)


def simcol_depth_errors(pred_unit: np.ndarray, gt_cm: np.ndarray, scale: float) -> dict[str, float]:
    """Challenge errors of ONE image: ``L1`` (cm), ``rel`` (median relative error, %), ``rmse`` (cm).

    Args:
        pred_unit: ``H x W`` prediction in ``[0, 1]`` (depth / 20 cm), already clipped.
        gt_cm: ``H x W`` GT depth in cm.
        scale: the sequence's scale from :func:`simcol_depth_scale`.
    """
    pred_unit, gt_cm = _same_shape_2d("pred_unit", pred_unit, "gt_cm", gt_cm)
    pred = np.asarray(pred_unit, dtype=np.float64) * scale * SIMCOL_DEPTH_RANGE_CM
    gt = np.asarray(gt_cm, dtype=np.float64)
    diff = pred - gt
    return {
        "l1": float(np.mean(np.abs(diff))),
        "rel": float(np.median(np.abs(diff) / (gt + SIMCOL_REL_EPS_CM)) * 100.0),
        "rmse": float(np.sqrt(np.mean(diff**2))),
    }


def simcol_depth_sequence(pred_cm: np.ndarray, gt_cm: np.ndarray) -> dict[str, object]:
    """The challenge's depth protocol over one sequence.

    Args:
        pred_cm: ``N x H x W`` predicted depth in cm (converted with :func:`depth_to_simcol_unit`).
        gt_cm: ``N x H x W`` GT depth in cm.

    Returns:
        ``scale``, the sequence means ``l1, rel, rmse`` and ``per_frame`` (dict of ``N`` arrays).
    """
    pred_cm = np.asarray(pred_cm)
    gt_cm = np.asarray(gt_cm)
    check_shape("gt_cm", gt_cm, "N,H,W", **check_shape("pred_cm", pred_cm, "N,H,W"))
    pred_unit = depth_to_simcol_unit(pred_cm)
    scale = simcol_depth_scale(pred_unit, gt_cm)
    per_frame = [simcol_depth_errors(p, g, scale) for p, g in zip(pred_unit, gt_cm)]
    columns = {key: np.array([f[key] for f in per_frame]) for key in SIMCOL_DEPTH_KEYS}
    return {"scale": scale, **{k: float(v.mean()) for k, v in columns.items()}, "per_frame": columns}


# ------------------------------------------------------------------------------------------- pose
def relative_poses(poses: np.ndarray) -> np.ndarray:
    """``Q_i = inv(P_i) @ P_{i+1}`` for ``N x 4 x 4`` camera-to-world poses -> ``(N-1) x 4 x 4``."""
    poses = _pose_stack(poses, "poses")
    return np.linalg.inv(poses[:-1]) @ poses[1:]


def chain_relative_poses(first: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Trajectory ``P_0 = first``, ``P_{i+1} = P_i @ Q_i``; returns ``(M+1) x 4 x 4``."""
    relative = _pose_stack(relative, "relative poses")
    trajectory = [np.asarray(first, dtype=np.float64)]
    for q in relative:
        trajectory.append(trajectory[-1] @ q)
    return np.stack(trajectory)


def fit_translation_scale(gt_translations: np.ndarray, pred_translations: np.ndarray) -> float:
    """Least-squares ``s`` minimising ``|gt - s * pred|^2`` over ``K x 3`` translations."""
    denominator = float(np.sum(pred_translations**2))
    if denominator <= 0:
        return 1.0  # nothing predicted moves: any scale gives the same (zero) trajectory
    return float(np.sum(gt_translations * pred_translations) / denominator)


def scaled_relative_poses(relative: np.ndarray, scale: float) -> np.ndarray:
    """Copy of ``relative`` with every translation multiplied by ``scale``."""
    scaled = np.array(relative, dtype=np.float64)
    scaled[:, :3, 3] *= scale
    return scaled


def simcol_pose_sequence(gt_poses: np.ndarray, pred_relative: np.ndarray) -> dict[str, object]:
    """The challenge's pose protocol over one sequence.

    Args:
        gt_poses: ``N x 4 x 4`` GT camera-to-world poses ``P_i``.
        pred_relative: ``(N-1) x 4 x 4`` predicted ``Q'_i`` (frame ``i+1`` into frame ``i``).

    Returns:
        ``scale``, ``ate`` (the challenge's, cm), ``ate_local`` (origin-independent, cm), ``rte`` (cm), ``rot``
        (degrees), ``trajectory`` (the chain of scaled ``Q'_i`` from ``P_0``, ``N x 4 x 4``) and ``per_frame``
        arrays ``rte``, ``rot`` (``N-1``), ``ate`` and ``ate_local`` (``N``). See the module docstring.
    """
    gt_poses = _pose_stack(gt_poses, "GT poses")
    pred_relative = _pose_stack(pred_relative, "predicted relative poses")
    if len(pred_relative) != len(gt_poses) - 1:
        raise ValueError(f"expected {len(gt_poses) - 1} relative poses for {len(gt_poses)} GT poses, "
                         f"got {len(pred_relative)}")
    gt_relative = relative_poses(gt_poses)
    scale = fit_translation_scale(gt_relative[:, :3, 3], pred_relative[:, :3, 3])
    pred_scaled = scaled_relative_poses(pred_relative, scale)
    trajectory = chain_relative_poses(gt_poses[0], pred_scaled)
    errors = np.linalg.inv(gt_relative) @ pred_scaled
    rte = np.linalg.norm(errors[:, :3, 3], axis=1)
    rot = rotation_angle_deg(errors[:, :3, :3])
    challenge_positions = scale * chain_relative_poses(gt_poses[0], pred_relative)[:, :3, 3]
    ate = np.linalg.norm(gt_poses[:, :3, 3] - challenge_positions, axis=1)
    ate_local = np.linalg.norm(gt_poses[:, :3, 3] - trajectory[:, :3, 3], axis=1)
    return {
        "scale": scale,
        "ate": float(np.median(ate)),
        "ate_local": float(np.median(ate_local)),
        "rte": float(np.median(rte)),
        "rot": float(np.median(rot)),
        "trajectory": trajectory,
        "per_frame": {"ate": ate, "ate_local": ate_local, "rte": rte, "rot": rot},
    }


def endoslam_pose_sequence(gt_poses: np.ndarray, pred_relative: np.ndarray) -> dict[str, float]:
    """EndoSLAM-style ATE (RMSE, cm) and RPE means over one sequence.

    Both trajectories start at ``P_0``; the predicted positions (relative to ``P_0``) get the least-squares
    scale onto the GT positions before ``ATE = sqrt(mean |t_gt - s t_pred|^2)``. RPE compares consecutive
    relative poses with that scale: ``rpe_trans`` mean ``|t(E_i)|`` (cm), ``rpe_rot`` mean angle (degrees).
    """
    gt_poses = _pose_stack(gt_poses, "GT poses")
    pred_relative = _pose_stack(pred_relative, "predicted relative poses")
    if len(pred_relative) != len(gt_poses) - 1:
        raise ValueError(f"expected {len(gt_poses) - 1} relative poses for {len(gt_poses)} GT poses, "
                         f"got {len(pred_relative)}")
    origin_inv = np.linalg.inv(gt_poses[0])
    gt_local = (origin_inv @ gt_poses)[:, :3, 3]
    pred_local = chain_relative_poses(np.eye(4), pred_relative)[:, :3, 3]
    scale = fit_translation_scale(gt_local, pred_local)
    ate = float(np.sqrt(np.mean(np.sum((gt_local - scale * pred_local) ** 2, axis=1))))
    errors = np.linalg.inv(relative_poses(gt_poses)) @ scaled_relative_poses(pred_relative, scale)
    return {
        "scale": scale,
        "ate": ate,
        "rpe_trans": float(np.mean(np.linalg.norm(errors[:, :3, 3], axis=1))),
        "rpe_rot": float(np.mean(rotation_angle_deg(errors[:, :3, :3]))),
    }


def motion_agreement(gt_poses: np.ndarray, pred_relative: np.ndarray) -> dict[str, float]:
    """The ``motion`` figures of one sequence (see the module docstring).

    Args:
        gt_poses: ``N x 4 x 4`` GT camera-to-world poses ``P_i``.
        pred_relative: ``(N-1) x 4 x 4`` predicted ``Q'_i`` (frame ``i+1`` into frame ``i``).

    Returns:
        ``step_corr``, ``forward_corr`` (z, the view direction), ``rotation_corr`` (in [-1, 1]), ``step_spread``
        (standard deviation of the predicted step lengths, scaled by the challenge's translation scale, over the
        true ones'; 1 when the path varies its speed as much as the camera) and ``direction_deg`` (median, over
        steps of at least :data:`DIRECTION_MIN_STEP_SHARE` of the median true step).
    """
    gt_poses = _pose_stack(gt_poses, "GT poses")
    pred_relative = _pose_stack(pred_relative, "predicted relative poses")
    if len(pred_relative) != len(gt_poses) - 1 or len(pred_relative) < 2:
        raise ValueError(f"expected {len(gt_poses) - 1} (at least 2) relative poses for {len(gt_poses)} GT poses, "
                         f"got {len(pred_relative)}")
    gt_relative = relative_poses(gt_poses)
    gt_t, pred_t = gt_relative[:, :3, 3], pred_relative[:, :3, 3]
    gt_step, pred_step = np.linalg.norm(gt_t, axis=1), np.linalg.norm(pred_t, axis=1)
    scale = abs(fit_translation_scale(gt_t, pred_t))
    # steps of a paused camera have no direction; a sequence that mostly pauses still has its moving ones
    moving = gt_step > max(DIRECTION_MIN_STEP_SHARE * float(np.median(gt_step)), 1e-9)
    cosine = np.sum(gt_t * pred_t, axis=1) / np.maximum(gt_step * pred_step, 1e-12)
    return {
        "step_corr": correlation(gt_step, pred_step),
        "forward_corr": correlation(gt_t[:, 2], pred_t[:, 2]),
        "rotation_corr": correlation(rotation_angle_deg(gt_relative[:, :3, :3]),
                                     rotation_angle_deg(pred_relative[:, :3, :3])),
        "step_spread": 0.0 if _constant(pred_step) else float(scale * np.std(pred_step) / max(float(np.std(gt_step)),
                                                                                               1e-12)),
        # a camera that never moves has no direction to find: none is wrong
        "direction_deg": float(np.median(np.degrees(np.arccos(np.clip(cosine[moving], -1.0, 1.0)))))
        if moving.any() else 0.0,
    }


def scale_consistency(gt_poses: np.ndarray, pred_relative: np.ndarray, depth_ratios: list[float]) -> dict[str, float]:
    """The ``scale`` figures of one sequence (see the module docstring).

    Args:
        gt_poses: ``N x 4 x 4`` GT camera-to-world poses ``P_i``.
        pred_relative: ``(N-1) x 4 x 4`` predicted ``Q'_i``.
        depth_ratios: the per-frame ``median(gt) / median(pred)`` of the predicted depth (the paper protocol's
            ``ratio``) of the same frames, in temporal order (frames without GT depth left out).
    """
    gt_poses = _pose_stack(gt_poses, "GT poses")
    pred_relative = _pose_stack(pred_relative, "predicted relative poses")
    if len(pred_relative) != len(gt_poses) - 1:
        raise ValueError(f"expected {len(gt_poses) - 1} relative poses for {len(gt_poses)} GT poses, "
                         f"got {len(pred_relative)}")
    ratios = np.asarray(depth_ratios, dtype=np.float64)
    if len(ratios) == 0 or not np.all(ratios > 0):
        raise ValueError(f"expected positive per-frame depth ratios, got {len(ratios)} of them")
    if not np.any(pred_relative[:, :3, 3]):
        raise ValueError("the predicted path does not move: it has no scale to compare with the depth's")
    path_scale = fit_translation_scale(relative_poses(gt_poses)[:, :3, 3], pred_relative[:, :3, 3])
    quarter = max(1, len(ratios) // 4)
    return {"path_over_depth": float(path_scale / np.median(ratios)),
            "depth_drift": float(np.median(ratios[-quarter:]) / np.median(ratios[:quarter]))}


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two series of the same length; 0 where either is constant (nothing varies together)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if _constant(a) or _constant(b):
        return 0.0
    a, b = a - a.mean(), b - b.mean()
    return float(np.clip(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)), -1.0, 1.0))


def _constant(series: np.ndarray) -> bool:
    # relative to the values' size: the rounding residue of a repeated step is no variation
    return float(np.ptp(series)) <= 1e-9 * float(np.max(np.abs(series)))


# -------------------------------------------------------------------------------------- helpers
def mean_over(records: list[dict[str, float]], keys: tuple[str, ...]) -> dict[str, float]:
    """Average each of ``keys`` over ``records`` (images or sequences)."""
    if not records:
        raise ValueError("nothing to average: no images or sequences were evaluated")
    return {key: float(np.mean([r[key] for r in records])) for key in keys}


def _image_means(stack: np.ndarray, name: str) -> np.ndarray:
    stack = np.asarray(stack, dtype=np.float64)
    check_shape(name, stack, "N,H,W")
    return stack.mean(axis=(1, 2))


def _same_shape_2d(a_name: str, a: np.ndarray, b_name: str, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a)
    b = np.asarray(b)
    check_shape(b_name, b, "H,W", **check_shape(a_name, a, "H,W"))
    return a, b


def _pose_stack(poses: np.ndarray, what: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    check_shape(what, poses, "N,4,4")
    if not np.isfinite(poses).all():
        raise ValueError(f"{what} contain non-finite values")
    return poses
