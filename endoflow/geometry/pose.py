"""Rigid poses: 6-DoF vectors, 4x4 matrices, inverses, relative poses, Unity <-> OpenCV handedness.

Conventions (see ``docs/architecture.md``):

- A pose ``T_a_b`` is a 4x4 rigid transform that maps points from frame ``b`` into frame ``a``:
  ``p_a = T_a_b @ p_b``. Absolute poses are camera-to-world, ``T_world_cam``.
- The relative pose used to warp a target frame t from a source frame s is
  ``T_s_t = inv(T_world_s) @ T_world_t``: it maps points in t's camera frame into s's.
- A 6-DoF pose vector is ``(rx, ry, rz, tx, ty, tz)``: an axis-angle rotation (direction = axis,
  norm = angle in radians) followed by a translation; ``T = [[R(r), t], [0, 0, 0, 1]]``.
- Quaternions are ``(qx, qy, qz, qw)``, scalar last, as SimCol3D stores them.

Torch functions are batched over any leading dimensions; :func:`invert_pose` and :func:`relative_pose`
also accept numpy arrays and return the same type.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from endoflow.shapes import check_shape

ArrayOrTensor = TypeVar("ArrayOrTensor", np.ndarray, torch.Tensor)

# Unity (left-handed, y up) <-> OpenCV (right-handed, y down): flip the y axis on both sides.
TM = np.diag([1.0, -1.0, 1.0, 1.0])


# ----------------------------------------------------------------------------------------- torch
def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` from axis-angle vectors ``[..., 3]`` (angle = norm, radians)."""
    check_shape("axis_angle", axis_angle, "...,3")
    lead = axis_angle.shape[:-1]
    flat = axis_angle.reshape(-1, 3)
    # kornia's Rodrigues has no low-precision path; compute in float32 at least.
    compute_dtype = torch.promote_types(flat.dtype, torch.float32)
    rotation = axis_angle_to_rotation_matrix(flat.to(compute_dtype))
    return rotation.to(axis_angle.dtype).reshape(*lead, 3, 3)


def matrix_to_axis_angle(rotation: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors ``[..., 3]`` (angle in [0, pi]) of rotation matrices ``[..., 3, 3]``."""
    check_shape("rotation", rotation, "...,3,3")
    lead = rotation.shape[:-2]
    compute_dtype = torch.promote_types(rotation.dtype, torch.float32)
    axis_angle = rotation_matrix_to_axis_angle(rotation.reshape(-1, 3, 3).to(compute_dtype))
    return axis_angle.to(rotation.dtype).reshape(*lead, 3)


def pose_vec_to_matrix(vec: torch.Tensor) -> torch.Tensor:
    """4x4 rigid transforms ``[..., 4, 4]`` from pose vectors ``[..., 6]`` = (axis-angle, translation)."""
    check_shape("vec", vec, "...,6")
    rotation = axis_angle_to_matrix(vec[..., :3])
    top = torch.cat([rotation, vec[..., 3:, None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def matrix_to_pose_vec(T: torch.Tensor) -> torch.Tensor:
    """Pose vectors ``[..., 6]`` = (axis-angle, translation) of rigid transforms ``[..., 4, 4]``.

    Inverse of :func:`pose_vec_to_matrix` for rotation angles below pi.
    """
    check_shape("T", T, "...,4,4")
    return torch.cat([matrix_to_axis_angle(T[..., :3, :3]), T[..., :3, 3]], dim=-1)


# ---------------------------------------------------------------------------------- torch + numpy
def invert_pose(T: ArrayOrTensor) -> ArrayOrTensor:
    """Rigid inverse ``[[R^T, -R^T t], [0, 1]]`` of ``[..., 4, 4]`` poses: ``T_a_b`` -> ``T_b_a``.

    Exact for rigid transforms and cheaper and better conditioned than a general matrix inverse.
    """
    check_shape("T", T, "...,4,4")
    rotation_t = T[..., :3, :3].swapaxes(-1, -2)
    translation = -(rotation_t @ T[..., :3, 3:4])
    if isinstance(T, torch.Tensor):
        inverse = torch.zeros_like(T)
    else:
        inverse = np.zeros_like(T)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3:4] = translation
    inverse[..., 3, 3] = 1
    return inverse


def relative_pose(T_world_s: ArrayOrTensor, T_world_t: ArrayOrTensor) -> ArrayOrTensor:
    """``T_s_t = inv(T_world_s) @ T_world_t``: maps points in t's camera frame into s's camera frame."""
    return invert_pose(T_world_s) @ T_world_t


def nearest_rigid(T: torch.Tensor) -> torch.Tensor:
    """``T [4, 4]`` with its rotation block replaced by the nearest rotation (:func:`nearest_rotation`) and its last
    row exact: a pose built by chaining inverses (which assume rigidity, :func:`invert_pose`) stays rigid however
    long the chain."""
    check_shape("T", T, "4,4")
    out = T.clone()
    out[:3, :3] = torch.from_numpy(nearest_rotation(T[:3, :3].detach().cpu().double().numpy())).to(T)
    out[3] = torch.tensor([0, 0, 0, 1], dtype=T.dtype, device=T.device)
    return out


# ------------------------------------------------------------------------------------------ numpy
def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation closest to ``matrix`` (SVD). The network's rotations are orthonormal only to float32
    rounding; chained over hundreds of frames that error grows until the path is no longer rigid (and the
    trajectory writers rightly refuse it), so every step and every chained pose is projected back."""
    u, _, vt = np.linalg.svd(matrix)
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] *= -1
    return u @ vt


def orthonormality_error(rotations: np.ndarray) -> np.ndarray:
    """``max |R^T R - I|`` of each ``[..., 3, 3]`` matrix: 0 for a rotation (and for a reflection; the determinant
    tells them apart)."""
    return np.abs(np.swapaxes(rotations, -1, -2) @ rotations - np.eye(3)).max(axis=(-2, -1))


def chain_step(T_world_prev: np.ndarray, T_cur_prev: np.ndarray) -> np.ndarray:
    """``T_world_cur = T_world_prev @ inv(T_cur_prev)``: the next camera-to-world pose of a path from the
    relative pose a pose network predicts, with the step's and the result's rotations kept rigid
    (:func:`nearest_rotation`)."""
    step = np.array(T_cur_prev, dtype=np.float64)
    step[:3, :3] = nearest_rotation(step[:3, :3])
    pose = np.asarray(T_world_prev, dtype=np.float64) @ invert_pose(step)
    pose[:3, :3] = nearest_rotation(pose[:3, :3])
    return pose


def mean_step(steps: np.ndarray) -> np.ndarray:
    """The constant-velocity step of ``N x 4 x 4`` relative poses: their mean pose vector (axis-angle,
    translation) as a ``4 x 4`` transform; the identity when ``N`` is 0."""
    check_shape("steps", steps, "...,4,4")
    if len(steps) == 0:
        return np.eye(4)
    vectors = matrix_to_pose_vec(torch.from_numpy(np.asarray(steps, np.float64))).numpy()
    return pose_vec_to_matrix(torch.from_numpy(np.mean(vectors, axis=0))).numpy()


def step_root(steps: np.ndarray, count: int) -> np.ndarray:
    """The per-frame steps ``S`` of ``N x 4 x 4`` relative poses ``T`` that each span ``count`` frames:
    ``S^count = T``, the step a camera at constant velocity repeats ``count`` times to move by ``T``.

    ``S`` turns about ``T``'s axis by a ``count``-th of its angle, and its translation ``t_S`` is the one those
    steps chain to ``t_T``: ``(I + R_S + ... + R_S^(count-1)) t_S = t_T``. Rotation angles below pi.
    """
    check_shape("steps", steps, "...,4,4")
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    steps = np.asarray(steps, np.float64)
    if count == 1:
        return steps.copy()
    turn = axis_angle_to_matrix(matrix_to_axis_angle(torch.from_numpy(steps[..., :3, :3])) / count).numpy()
    chained = np.zeros_like(turn)
    power = np.broadcast_to(np.eye(3), turn.shape).copy()
    for _ in range(count):
        chained += power
        power = power @ turn
    roots = np.broadcast_to(np.eye(4), steps.shape).copy()
    roots[..., :3, :3] = turn
    roots[..., :3, 3] = np.linalg.solve(chained, steps[..., :3, 3:4])[..., 0]
    return roots


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle of ``... x 3 x 3`` matrices in degrees, trace clipped so rounding never gives NaN."""
    trace = np.trace(rotations, axis1=-2, axis2=-1)
    return np.degrees(np.arccos((np.clip(trace, -1.0, 3.0) - 1.0) / 2.0))


def motion_statistics(T_world_cam: np.ndarray) -> dict[str, float]:
    """How a camera moves from frame to frame, the figures a pose network's task depends on (medians over the
    ``N - 1`` steps ``Q_i = inv(P_i) @ P_{i+1}`` of ``N x 4 x 4`` camera-to-world poses in cm):
    ``step_mm`` ``|t(Q_i)|``, ``rotation_deg`` the angle of ``R(Q_i)``, ``step_change_mm``
    ``|t(Q_{i+1}) - t(Q_i)|`` and ``rotation_change_deg`` the angle of ``R(Q_i)^T R(Q_{i+1})`` (how far the
    motion departs from constant velocity), and ``forward_share`` the share of steps along the camera's view
    (positive z)."""
    check_shape("T_world_cam", T_world_cam, "...,4,4")
    if len(T_world_cam) < 3:
        raise ValueError(f"motion statistics need at least 3 poses, got {len(T_world_cam)}")
    steps = relative_pose(T_world_cam[:-1], T_world_cam[1:])
    translation, rotation = steps[:, :3, 3], steps[:, :3, :3]
    return {
        "step_mm": float(np.median(np.linalg.norm(translation, axis=1)) * 10),
        "rotation_deg": float(np.median(rotation_angle_deg(rotation))),
        "step_change_mm": float(np.median(np.linalg.norm(np.diff(translation, axis=0), axis=1)) * 10),
        "rotation_change_deg": float(np.median(rotation_angle_deg(
            np.swapaxes(rotation[:-1], 1, 2) @ rotation[1:]))),
        "forward_share": float(np.mean(translation[:, 2] > 0)),
    }


def quaternion_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` from quaternions ``[..., 4]`` (qx, qy, qz, qw; scalar last).

    Quaternions are normalised first; ``q`` and ``-q`` give the same matrix (sign flips in the data are
    harmless).
    """
    q = np.asarray(q, dtype=np.float64)
    check_shape("q", q, "...,4")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("quaternion of zero norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def matrix_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[..., 4]`` (qx, qy, qz, qw) of rotation matrices ``[..., 3, 3]``, with qw >= 0."""
    R = np.asarray(R, dtype=np.float64)
    check_shape("R", R, "...,3,3")
    # Each of 4 equivalent formulas divides by one component; use the largest one for stability.
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    squares = np.stack(
        [
            1 + 2 * R[..., 0, 0] - trace,
            1 + 2 * R[..., 1, 1] - trace,
            1 + 2 * R[..., 2, 2] - trace,
            1 + trace,
        ],
        axis=-1,
    )
    largest = np.argmax(squares, axis=-1)
    big = np.sqrt(np.maximum(np.take_along_axis(squares, largest[..., None], -1)[..., 0], 0)) / 2
    scale = 1 / (4 * big)
    xy, xz, yz = R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    wx, wy, wz = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    candidates = np.stack(
        [
            np.stack([big, xy * scale, xz * scale, wx * scale], -1),
            np.stack([xy * scale, big, yz * scale, wy * scale], -1),
            np.stack([xz * scale, yz * scale, big, wz * scale], -1),
            np.stack([wx * scale, wy * scale, wz * scale, big], -1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(candidates, largest[..., None, None], -2)[..., 0, :]
    q = np.where(q[..., 3:4] < 0, -q, q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def unity_to_opencv(M: np.ndarray) -> np.ndarray:
    """SimCol3D's official handedness conversion ``P = TM @ M @ TM`` with ``TM = diag(1, -1, 1, 1)``.

    ``M`` is a Unity (left-handed) camera-to-world ``[..., 4, 4]``; ``P`` is right-handed OpenCV with the
    camera looking along +z.
    """
    M = np.asarray(M, dtype=np.float64)
    check_shape("M", M, "...,4,4")
    return TM @ M @ TM


def opencv_to_unity(P: np.ndarray) -> np.ndarray:
    """Inverse of :func:`unity_to_opencv` (``TM`` is its own inverse)."""
    P = np.asarray(P, dtype=np.float64)
    check_shape("P", P, "...,4,4")
    return TM @ P @ TM
