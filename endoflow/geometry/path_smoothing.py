"""A camera path's rotation smoothed over a window of frames: each step's rotation (its axis-angle) becomes the
Gaussian-weighted mean of the steps around it, and the path is chained again from its first pose with each step's
translation as it was (in the step's own camera frame).

Why: between consecutive 64 px frames a colonoscope turns the image by a tenth of a pixel, and the refined path's
rotation per frame is the difference of two keyframe alignments whose errors change from frame to frame, while the
camera's angular velocity changes over tens of frames (the built-in paths' true steps smoothed over 3 frames move by
0.002-0.004 degrees). Averaging each step with its neighbours removes that jitter and keeps the turns; where the
error is the same from frame to frame (depth of the wrong shape), it stays. The translations are untouched, so
the path's length, speed changes and scale are the refined path's. Measured: docs/results.md, "The refined path's
rotation smoothed".

The window reaches ``ceil(3 * sigma)`` steps either way and is cut at the path's ends (its weights renormalised),
so a path that turns at a constant rate is returned as it is. :class:`StepRotationSmoother` does it as frames
stream: each pose comes out once the frames its window reaches have arrived, ``reach`` frames later, or at
:meth:`~StepRotationSmoother.flush`; :func:`smooth_path_rotations` is the same over a whole path.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Generic, TypeVar

import numpy as np
import torch

from endoflow.geometry.pose import axis_angle_to_matrix, invert_pose, matrix_to_axis_angle, nearest_rotation
from endoflow.shapes import check_shape

Payload = TypeVar("Payload")
GAUSSIAN_REACH = 3.0  # the window ends this many standard deviations from its centre


def smoothing_reach(sigma_frames: float) -> int:
    """How many steps the window of standard deviation ``sigma_frames`` reaches on either side (0 for 0)."""
    if not sigma_frames >= 0:
        raise ValueError(f"the smoothing's standard deviation must be >= 0 frames, got {sigma_frames}")
    return math.ceil(GAUSSIAN_REACH * sigma_frames)


class StepRotationSmoother(Generic[Payload]):
    """Smooths a streamed path's step rotations (module docstring): :meth:`push` each camera-to-world pose with
    whatever belongs to its frame, and take back the frames whose smoothed pose is known, in order, as
    ``(payload, T_world_cam)``; :meth:`flush` hands back the rest once the path ends. ``sigma_frames`` 0 hands
    every frame back at once, unchanged. Memory: the window's steps (``2 * reach + 1`` at most) and the frames held
    back (``reach``)."""

    def __init__(self, sigma_frames: float) -> None:
        self.reach = smoothing_reach(sigma_frames)
        self.sigma_frames = sigma_frames
        offsets = np.arange(-self.reach, self.reach + 1)
        self._weights = np.exp(-0.5 * (offsets / sigma_frames) ** 2) if self.reach else np.ones(1)
        self._steps: deque[tuple[np.ndarray, np.ndarray]] = deque()  # (axis-angle, translation) of each step
        self._first_step = 0  # the path's index of the step _steps[0]
        self._last_raw: np.ndarray | None = None
        self._waiting: deque[Payload] = deque()
        self._emitted = 0  # frames handed back so far
        self._last_emitted: np.ndarray | None = None

    def push(self, T_world_cam: np.ndarray, payload: Payload) -> list[tuple[Payload, np.ndarray]]:
        """Take the next frame's pose ``[4, 4]``; returns the frames now settled."""
        check_shape("T_world_cam", T_world_cam, "4,4")
        pose = np.asarray(T_world_cam, dtype=np.float64)
        if self.reach == 0:
            self._waiting.append(payload)
            return [self._emit(pose)]
        if self._last_raw is not None:
            step = invert_pose(self._last_raw) @ pose
            rotation = matrix_to_axis_angle(torch.from_numpy(nearest_rotation(step[:3, :3]))).numpy()
            self._steps.append((rotation, step[:3, 3].copy()))
        self._last_raw = pose
        self._waiting.append(payload)
        if self._emitted == 0:
            return [self._emit(pose)]
        settled = []
        # frame i needs step i - 1 and the steps its window reaches beyond it: up to i - 1 + reach
        while self._waiting and self._steps_known() >= self._emitted + self.reach:
            settled.append(self._emit(self._chained_next()))
        return settled

    def flush(self) -> list[tuple[Payload, np.ndarray]]:
        """The frames still held back, their windows cut at the path's end."""
        return [self._emit(self._chained_next()) for _ in range(len(self._waiting))]

    def _steps_known(self) -> int:
        return self._first_step + len(self._steps)

    def _chained_next(self) -> np.ndarray:
        """The next frame's pose: the last one handed back, moved by its step with the smoothed rotation (the
        window cut to the steps there are: at the path's start, and at its end once it has ended)."""
        index = self._emitted - 1  # the step into the next frame
        lo, hi = max(index - self.reach, self._first_step), min(index + self.reach, self._steps_known() - 1)
        weights = self._weights[lo - index + self.reach:hi - index + self.reach + 1]
        rotations = np.stack([self._steps[j - self._first_step][0] for j in range(lo, hi + 1)])
        mean = (weights[:, None] * rotations).sum(axis=0) / weights.sum()
        step = np.eye(4)
        step[:3, :3] = axis_angle_to_matrix(torch.from_numpy(mean)).numpy()
        step[:3, 3] = self._steps[index - self._first_step][1]
        pose = self._last_emitted @ step
        pose[:3, :3] = nearest_rotation(pose[:3, :3])
        self._forget_before(index + 1 - self.reach)
        return pose

    def _forget_before(self, index: int) -> None:
        while self._steps and self._first_step < index:
            self._steps.popleft()
            self._first_step += 1

    def _emit(self, pose: np.ndarray) -> tuple[Payload, np.ndarray]:
        self._emitted += 1
        self._last_emitted = pose
        return self._waiting.popleft(), pose


def smooth_path_rotations(T_world_cam: np.ndarray, sigma_frames: float) -> np.ndarray:
    """``[N, 4, 4]`` camera-to-world poses with their step rotations smoothed (module docstring); the first pose and
    every step's translation as they were."""
    check_shape("T_world_cam", T_world_cam, "N,4,4")
    smoother: StepRotationSmoother[None] = StepRotationSmoother(sigma_frames)
    settled = [pose for frame in T_world_cam for _, pose in smoother.push(frame, None)] + \
              [pose for _, pose in smoother.flush()]
    return np.stack(settled) if settled else np.zeros((0, 4, 4))
