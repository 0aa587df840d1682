"""A camera path's orientations smoothed over a window of frames, its positions as they were.

Each frame's orientation ``R_i`` is replaced by the value at frame ``i`` of a straight line fitted, weighted by a
Gaussian of ``sigma`` frames, to the orientations around it, in the tangent space at ``R_i``: with
``d_k = log(R_i^T R_(i+k))`` (axis-angle) and weights ``w_k = exp(-k^2 / (2 sigma^2))`` for ``|k| <= reach``, the
intercept ``a`` of the weighted least-squares line ``d_k ~ a + k b`` gives ``R_i exp(a)``. Inside a path the window is
symmetric and ``a`` is the Gaussian mean of the ``d_k``; at the path's ends, where the window is cut, the line's
slope keeps a turning camera's orientation where it is instead of pulling it towards the frames inside. A camera
that turns at a constant rate is returned as it is, ends included; every orientation stays anchored to its own
frame's, so nothing drifts however long the path.

Why: the refined path's rotation between consecutive frames is the difference of two keyframe alignments, and at
64 px a frame's rotation moves the image by a tenth of a pixel, so each alignment's error is a sizeable share of the
motion and changes from frame to frame; a colonoscope's angular velocity changes over tens of frames (the built-in
paths' true orientations smoothed over 3 frames move by 0.004 degrees). The fit takes the jitter out and keeps the
turns; an error that is the same from frame to frame (depth of the wrong shape) stays. Measured: docs/results.md,
"The refined path's rotation smoothed".

:class:`OrientationSmoother` does it as frames stream: each frame comes back once the frames its window reaches have
arrived, ``reach`` (``ceil(3 sigma)``) frames later, or at :meth:`~OrientationSmoother.flush`;
:func:`smooth_path_orientations` is the same over a whole path.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Generic, TypeVar

import numpy as np
import torch

from endoflow.geometry.pose import axis_angle_to_matrix, matrix_to_axis_angle, nearest_rotation
from endoflow.shapes import check_shape

Payload = TypeVar("Payload")
GAUSSIAN_REACH = 3.0  # the window ends this many standard deviations from its centre


def smoothing_reach(sigma_frames: float) -> int:
    """How many frames the window of standard deviation ``sigma_frames`` reaches on either side (0 for 0)."""
    if not 0 <= sigma_frames < math.inf:
        raise ValueError(f"the smoothing's standard deviation must be finite and >= 0 frames, got {sigma_frames}")
    return math.ceil(GAUSSIAN_REACH * sigma_frames)


class OrientationSmoother(Generic[Payload]):
    """Smooths a streamed path's orientations (module docstring): :meth:`push` each camera-to-world pose with
    whatever belongs to its frame, and take back the frames whose smoothed pose is known, in order, as
    ``(payload, T_world_cam)``; :meth:`flush` hands back the rest once the path ends. ``sigma_frames`` 0 hands
    every frame back at once, unchanged. It holds the window's poses (``2 * reach + 1`` at most) and the frames
    not yet handed back (``reach`` at most)."""

    def __init__(self, sigma_frames: float) -> None:
        self.reach = smoothing_reach(sigma_frames)
        self.sigma_frames = sigma_frames
        offsets = np.arange(-self.reach, self.reach + 1)
        self._weights = np.exp(-0.5 * (offsets / sigma_frames) ** 2) if self.reach else np.ones(1)
        self._window: deque[np.ndarray] = deque()  # the poses of frames _first, _first + 1, ...
        self._first = 0
        self._waiting: deque[Payload] = deque()  # the payloads of frames _next, _next + 1, ...
        self._next = 0

    def push(self, T_world_cam: np.ndarray, payload: Payload) -> list[tuple[Payload, np.ndarray]]:
        """Take the next frame's pose ``[4, 4]``; returns the frames now settled."""
        check_shape("T_world_cam", T_world_cam, "4,4")
        pose = np.asarray(T_world_cam, dtype=np.float64)
        if not np.isfinite(pose).all():
            raise ValueError(f"T_world_cam of frame {self._first + len(self._window)} is not finite: {pose.tolist()}")
        if self.reach == 0:
            return [(payload, pose)]
        self._window.append(pose)
        self._waiting.append(payload)
        newest = self._first + len(self._window) - 1
        settled = []
        while self._waiting and newest >= self._next + self.reach:
            settled.append(self._settle())
        return settled

    def flush(self) -> list[tuple[Payload, np.ndarray]]:
        """The frames still held back, their windows cut at the path's end."""
        return [self._settle() for _ in range(len(self._waiting))]

    def _settle(self) -> tuple[Payload, np.ndarray]:
        """The next frame with its orientation fitted over the window there is around it."""
        i = self._next
        lo, hi = max(i - self.reach, self._first), min(i + self.reach, self._first + len(self._window) - 1)
        window = np.stack([self._window[j - self._first] for j in range(lo, hi + 1)])
        pose = self._window[i - self._first].copy()
        offsets = np.arange(lo, hi + 1) - i
        pose[:3, :3] = nearest_rotation(pose[:3, :3] @ _fitted_correction(
            pose[:3, :3], window[:, :3, :3], offsets, self._weights[offsets + self.reach]))
        self._next += 1
        while self._first < self._next - self.reach:
            self._window.popleft()
            self._first += 1
        return self._waiting.popleft(), pose


def _fitted_correction(R: np.ndarray, rotations: np.ndarray, offsets: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``exp(a)`` ``[3, 3]``: ``a`` the intercept of the weighted least-squares line through the axis-angles of
    ``R^T rotations`` (``[m, 3, 3]``) against the frame ``offsets`` ``[m]`` (``R`` at offset 0); the weighted mean
    where the offsets cannot fix a slope (a single frame)."""
    logs = matrix_to_axis_angle(torch.from_numpy(R.T @ rotations)).numpy()
    s0, s1, s2 = weights.sum(), weights @ offsets, weights @ offsets ** 2
    mean, moment = weights @ logs, (weights * offsets) @ logs
    determinant = s0 * s2 - s1 ** 2
    intercept = (s2 * mean - s1 * moment) / determinant if determinant > 1e-12 * s0 ** 2 else mean / s0
    return axis_angle_to_matrix(torch.from_numpy(intercept)).numpy()


def smooth_path_orientations(T_world_cam: np.ndarray, sigma_frames: float) -> np.ndarray:
    """``[N, 4, 4]`` camera-to-world poses with their orientations smoothed (module docstring), positions as they
    were."""
    check_shape("T_world_cam", T_world_cam, "N,4,4")
    smoother: OrientationSmoother[None] = OrientationSmoother(sigma_frames)
    settled = [pose for frame in T_world_cam for _, pose in smoother.push(frame, None)] + \
              [pose for _, pose in smoother.flush()]
    return np.stack(settled) if settled else np.zeros((0, 4, 4))
