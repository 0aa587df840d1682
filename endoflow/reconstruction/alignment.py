"""A reconstructed camera path aligned onto its ground truth: one transform for the figures the measurement
scores (:mod:`endoflow.reconstruction.measure`) and the ground-truth path the contact sheet draws.

Umeyama on positions, as ``evo``'s ``align``: Sim(3) for the model (monocular: its scale is unknown), SE(3) for
a path of metric scale (the constant-velocity baseline). Positions in cm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np


@dataclass(frozen=True)
class Alignment:
    """``p_gt = scale * R @ p + t``: maps a reconstruction's world into the ground truth's."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.rotation.T + self.translation

    def invert(self, points_gt: np.ndarray) -> np.ndarray:
        """Ground-truth points in the reconstruction's world."""
        return (points_gt - self.translation) @ self.rotation / self.scale


def align_trajectory(estimate, reference, with_scale: bool) -> Alignment:
    """Align ``evo`` trajectory ``estimate`` onto ``reference`` in place (Umeyama on positions, ``evo``'s
    ``align``); a path too short or too straight to fix a rotation is aligned at its first pose instead (and
    scaled by the ratio of path lengths)."""
    from evo.core.geometry import GeometryException

    first_gt, first = reference.poses_se3[0].copy(), estimate.poses_se3[0].copy()
    try:
        rotation, translation, scale = estimate.align(reference, correct_scale=with_scale)
        return Alignment(np.asarray(rotation), np.asarray(translation), float(scale))
    except GeometryException:
        scale = _length_ratio(reference.positions_xyz, estimate.positions_xyz) if with_scale else 1.0
        transform = first_gt @ np.linalg.inv(first)
        estimate.scale(scale)
        estimate.align_origin(reference)
        return Alignment(transform[:3, :3], first_gt[:3, 3] - scale * transform[:3, :3] @ first[:3, 3], scale)


def _length_ratio(reference: np.ndarray, estimate: np.ndarray) -> float:
    length = float(np.linalg.norm(np.diff(estimate, axis=0), axis=1).sum())
    return float(np.linalg.norm(np.diff(reference, axis=0), axis=1).sum()) / length if length > 0 else 1.0


def trajectories(gt_poses: np.ndarray, poses: np.ndarray):
    """``(reference, estimate)``: ``evo`` trajectories of ``N x 4 x 4`` camera-to-world poses, one per frame."""
    from evo.core.trajectory import PoseTrajectory3D

    stamps = np.arange(len(gt_poses), dtype=np.float64)
    return (PoseTrajectory3D(poses_se3=list(gt_poses), timestamps=stamps),
            PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps))


def ground_truth_in_path_world(gt_poses: Sequence[Optional[np.ndarray]], poses: Sequence[np.ndarray]
                               ) -> Optional[np.ndarray]:
    """``N x 3`` ground-truth camera positions mapped into the model path's world by the inverse of the Sim(3)
    alignment the measurement scores the path with; None unless every frame has a ground-truth pose."""
    if not poses or len(gt_poses) != len(poses) or any(pose is None for pose in gt_poses):
        return None
    gt = np.stack([np.asarray(pose, np.float64) for pose in gt_poses])
    reference, estimate = trajectories(gt, np.stack(poses))
    return align_trajectory(estimate, reference, with_scale=True).invert(gt[:, :3, 3])
