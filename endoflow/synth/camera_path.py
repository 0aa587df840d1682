"""A colonoscope-like camera trajectory along a tube: poses ``T_world_cam`` (OpenCV, cm), exact by construction.

The camera advances along a smoothed copy of the centreline (mostly forward, 1 to 2 mm per frame with a
smoothly varying speed), drifts gently off it, and turns a little around the local direction of the tube
(yaw and pitch of a few degrees, a slow roll). Every motion is a sum of slow sinusoids, so consecutive
frames differ by small, smooth rigid motions as in a real withdrawal or insertion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from endoflow.synth.tube import Tube

CENTRELINE_STEP_CM = 0.05
CENTRELINE_SMOOTHING_CM = 1.0


@dataclass
class MotionStyle:
    speed: tuple[float, float]  # cm per frame (range of the smoothly varying speed)
    lateral: float  # largest drift off the centreline, as a fraction of the narrowest nearby radius
    turn_deg: float  # largest yaw / pitch away from the tube's direction
    roll_deg: float  # largest roll around the tube's direction


def trajectory_arcs(frames: int, motion: MotionStyle, start: float, rng: np.random.Generator) -> np.ndarray:
    """Arc length of the camera at each frame: a smoothly varying forward speed within ``motion.speed``."""
    low, high = motion.speed
    wave = _slow_wave(frames, rng, periods=(25.0, 90.0))
    speeds = low + (high - low) * (0.5 + 0.5 * wave)
    return start + np.concatenate([[0.0], np.cumsum(speeds[:-1])])


def camera_poses(tube: Tube, arcs: np.ndarray, motion: MotionStyle, rng: np.random.Generator) -> np.ndarray:
    """``[F, 4, 4]`` camera-to-world poses at arc lengths ``arcs`` (OpenCV: x right, y down, z forward)."""
    frames = len(arcs)
    path = _smoothed_centreline(tube, arcs.min() - 3.0, arcs.max() + 3.0)
    centre = path(arcs)
    tangent = path(arcs + CENTRELINE_STEP_CM) - path(arcs - CENTRELINE_STEP_CM)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    across, down = _transported_frames(tangent, tube.e1[tube.slab_containing(centre[0])])

    narrowest = np.array([tube.radius_at(np.linspace(s - 1.0, s + 1.0, 41)).min() for s in arcs])
    drift_x = motion.lateral * narrowest * _slow_wave(frames, rng, periods=(40.0, 150.0))
    drift_y = motion.lateral * narrowest * _slow_wave(frames, rng, periods=(40.0, 150.0))
    position = centre + drift_x[:, None] * across + drift_y[:, None] * down

    roll = np.radians(motion.roll_deg) * _slow_wave(frames, rng, periods=(60.0, 200.0))
    yaw = np.radians(motion.turn_deg) * _slow_wave(frames, rng, periods=(20.0, 60.0))
    pitch = np.radians(motion.turn_deg) * _slow_wave(frames, rng, periods=(20.0, 60.0))
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for f in range(frames):
        x = np.cos(roll[f]) * across[f] + np.sin(roll[f]) * down[f]
        y = np.cross(tangent[f], x)
        base = np.stack([x, y, tangent[f]], axis=1)
        poses[f, :3, :3] = base @ _rotation_y(yaw[f]) @ _rotation_x(pitch[f])
        poses[f, :3, 3] = position[f]
    return poses


def _slow_wave(frames: int, rng: np.random.Generator, periods: tuple[float, float]) -> np.ndarray:
    """A smooth random signal in [-1, 1] over frames: two sinusoids with periods (in frames) in ``periods``."""
    period = rng.uniform(*periods, size=2)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    weight = rng.uniform(0.3, 1.0, size=2)
    f = np.arange(frames)[:, None]
    wave = (weight * np.sin(2 * np.pi * f / period + phase)).sum(axis=1)
    return wave / weight.sum()


def _smoothed_centreline(tube: Tube, start: float, stop: float):
    """The centreline polyline low-pass filtered along its arc length, as an interpolating function."""
    grid = np.arange(start, stop + CENTRELINE_STEP_CM, CENTRELINE_STEP_CM)
    points = tube.centreline_at(np.clip(grid, 0, tube.length))
    sigma = CENTRELINE_SMOOTHING_CM / CENTRELINE_STEP_CM
    offsets = np.arange(-int(3 * sigma), int(3 * sigma) + 1)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(points, ((len(offsets) // 2, len(offsets) // 2), (0, 0)), mode="edge")
    smooth = np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(3)], axis=1)

    def at(arcs: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(arcs, grid, smooth[:, i]) for i in range(3)], axis=1)

    return at


def _transported_frames(tangent: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-minimising normal pairs along unit tangents, starting from ``reference`` (no twisting)."""
    across = np.zeros_like(tangent)
    x = reference
    for f, t in enumerate(tangent):
        x = x - (x @ t) * t
        x /= np.linalg.norm(x)
        across[f] = x
    return across, np.cross(tangent, across)


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
