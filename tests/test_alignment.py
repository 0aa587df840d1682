"""The alignment of a reconstructed path onto its ground truth, which the measurement scores and the contact sheet
draws: the ground truth of a path that is exact up to a similarity comes back onto the path."""

from __future__ import annotations

import math

import numpy as np

from endoflow.reconstruction.alignment import ground_truth_in_path_world


def curved_path(count: int) -> list[np.ndarray]:
    poses = []
    for i in range(count):
        pose = np.eye(4)
        angle = 0.1 * i
        pose[:3, :3] = [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0,
                                                                                   math.cos(angle)]]
        pose[:3, 3] = [math.sin(i / 4), 0.05 * i * i, 0.5 * i]
        poses.append(pose)
    return poses


def similarity(scale: float) -> np.ndarray:
    c, s = math.cos(0.7), math.sin(0.7)
    transform = np.eye(4)
    transform[:3, :3] = scale * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    transform[:3, 3] = [3.0, -1.0, 5.0]
    return transform


def test_a_path_exact_up_to_a_similarity_gets_its_ground_truth_drawn_on_it():
    path = curved_path(12)
    transform = similarity(2.5)
    truth = []
    for pose in path:
        moved = transform @ pose
        moved[:3, :3] /= 2.5  # a camera pose keeps a rotation; only its position is scaled
        truth.append(moved)
    drawn = ground_truth_in_path_world(truth, path)
    np.testing.assert_allclose(drawn, np.stack(path)[:, :3, 3], atol=1e-9)


def test_no_ground_truth_is_drawn_unless_every_frame_has_a_pose():
    path = curved_path(5)
    assert ground_truth_in_path_world([*path[:4], None], path) is None
    assert ground_truth_in_path_world([], []) is None
