"""The evaluation's trivial baselines: what each predicts, on the same frames as the model.

They predict from the training set's statistics that training computes from the train shards and stores in the
model file (:class:`~endoflow.models.model_file.TrainingBaselines`); the evaluation only reads them there.

- ``constant_depth``: the training set's mean GT depth everywhere;
- ``mean_depth_map``: the training set's per-pixel mean GT depth map (resized where the stored size differs);
- ``constant_velocity``: every step between consecutive frames is the training set's mean relative pose of one
  frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from endoflow.models.model_file import TrainingBaselines

DEPTH_BASELINES = ("constant_depth", "mean_depth_map")
POSE_BASELINES = ("constant_velocity",)


def baseline_depths(training: TrainingBaselines, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """Each depth baseline's ``H x W`` float32 depth in cm at ``shape``."""
    mean_map = training.mean_depth_map
    if mean_map.shape != tuple(shape):
        mean_map = cv2.resize(mean_map, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return {"constant_depth": np.full(shape, training.mean_depth_cm, np.float32),
            "mean_depth_map": mean_map.astype(np.float32)}


def baseline_relative_poses(training: TrainingBaselines, steps: int) -> dict[str, np.ndarray]:
    """Each pose baseline's ``steps x 4 x 4`` relative poses ``inv(P_i) @ P_{i+1}`` between consecutive frames."""
    return {"constant_velocity": np.repeat(np.asarray(training.mean_relative_pose)[None], steps, axis=0)}
