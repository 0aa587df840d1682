"""A colonoscope-like camera trajectory along a tube: poses ``T_world_cam`` (OpenCV, cm), exact by construction.

Smooth phases of advancing, withdrawing and pausing along the centreline, with slow drift, sway, roll and now
and then a deliberate turn, calibrated on real SimCol3D poses; a test sequence follows a script that crosses every
change of motion. See docs/synthetic_data.md, "Camera, light and mucosa".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from endoflow.synth.tube import Tube

CENTRELINE_STEP_CM = 0.05
# the camera moves along the centreline smoothed over the first length, and looks along it smoothed over the
# second: a scope's tip does not turn with every bend of the lumen
CENTRELINE_SMOOTHING_CM = 1.0
VIEW_SMOOTHING_CM = 6.0
RAMP_FRAMES = 12  # speed changes between phases spread over this many frames
PHASES = ("advance", "withdraw", "pause")
# What a test sequence's camera does, in order, each phase about a quarter of its frames: every change a colonoscope
# makes, so that a path repeating one step cannot pass for one that follows the camera. (phase, speed as a share
# of MotionStyle.speed's range: 0 its slowest, 1 its fastest); a turn starts within TEST_TURN_START.
TEST_SCRIPT = (("advance", 0.0), ("pause", 0.0), ("withdraw", 0.5), ("advance", 1.0))
TEST_PHASE_JITTER = 0.2  # each phase's share of the frames varies by up to this fraction
TEST_TURN_START = (0.3, 0.6)  # as shares of the frames


@dataclass
class MotionStyle:
    """How the camera moves; lengths in cm, angles in degrees, durations in frames."""

    speed: tuple[float, float]  # cm per frame while advancing or withdrawing (drawn per phase)
    phase_shares: tuple[float, float, float]  # chance of a phase advancing, withdrawing, pausing
    phase_frames: tuple[int, int]  # length of one phase
    lateral: float  # largest drift off the centreline, as a fraction of the narrowest nearby radius
    sway_deg: float  # largest slow yaw / pitch away from the tube's direction
    roll_deg: float  # largest slow roll around the tube's direction
    turn_deg: tuple[float, float]  # how far one deliberate turn swings the view
    turn_frames: tuple[int, int]  # how long one turn takes
    turns_per_100_frames: float


def trajectory_arcs(frames: int, motion: MotionStyle, start: float, rng: np.random.Generator) -> np.ndarray:
    """Arc length of the camera at each frame, never behind ``start``: phases of advancing, withdrawing and
    pausing (the first advances), each at its own speed within ``motion.speed``, with ramps between."""
    speeds = np.zeros(frames)
    position, phase = 0, "advance"
    while position < frames:
        length = int(rng.integers(motion.phase_frames[0], motion.phase_frames[1] + 1))
        speed = rng.uniform(*motion.speed)
        speeds[position:position + length] = {"advance": speed, "withdraw": -speed, "pause": 0.0}[phase]
        position += length
        phase = PHASES[int(rng.choice(3, p=np.asarray(motion.phase_shares) / np.sum(motion.phase_shares)))]
    return _arcs_from_speeds(speeds, start)


def scripted_arcs(frames: int, motion: MotionStyle, start: float, rng: np.random.Generator) -> np.ndarray:
    """Arc length of a test sequence's camera at each frame, never behind ``start``: the phases of
    :data:`TEST_SCRIPT` in order (a slow advance, a pause, a withdrawal, a fast advance), their lengths jittered,
    with the same ramps between them as :func:`trajectory_arcs`."""
    shares = rng.uniform(1 - TEST_PHASE_JITTER, 1 + TEST_PHASE_JITTER, size=len(TEST_SCRIPT))
    bounds = np.round(np.concatenate([[0.0], np.cumsum(shares)]) / shares.sum() * frames).astype(int)
    slowest, fastest = motion.speed
    speeds = np.zeros(frames)
    for (phase, share), begin, end in zip(TEST_SCRIPT, bounds[:-1], bounds[1:]):
        speed = slowest + share * (fastest - slowest)
        speeds[begin:end] = {"advance": speed, "withdraw": -speed, "pause": 0.0}[phase]
    return _arcs_from_speeds(speeds, start)


def _arcs_from_speeds(speeds: np.ndarray, start: float) -> np.ndarray:
    """Arc lengths of per-frame speeds with each change spread over :data:`RAMP_FRAMES`, never behind ``start``."""
    frames = len(speeds)
    ramp = np.hanning(RAMP_FRAMES + 2)[1:-1]
    smooth = np.convolve(np.pad(speeds, RAMP_FRAMES, mode="edge"), ramp / ramp.sum(), mode="same")
    arcs = np.concatenate([[0.0], np.cumsum(smooth[RAMP_FRAMES:RAMP_FRAMES + frames - 1])])
    return start + arcs - min(arcs.min(), 0.0)


def camera_poses(tube: Tube, arcs: np.ndarray, motion: MotionStyle, rng: np.random.Generator,
                 scripted: bool = False) -> np.ndarray:
    """``[F, 4, 4]`` camera-to-world poses at arc lengths ``arcs`` (OpenCV: x right, y down, z forward); a
    ``scripted`` (test) sequence turns exactly once, starting within :data:`TEST_TURN_START`."""
    frames = len(arcs)
    path = _smoothed_centreline(tube, arcs.min() - 3.0, arcs.max() + 3.0, CENTRELINE_SMOOTHING_CM)
    view = _smoothed_centreline(tube, arcs.min() - 3.0, arcs.max() + 3.0, VIEW_SMOOTHING_CM)
    centre = path(arcs)
    tangent = view(arcs + CENTRELINE_STEP_CM) - view(arcs - CENTRELINE_STEP_CM)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    across, down = _transported_frames(tangent, tube.e1[tube.slab_containing(centre[0])])

    narrowest = np.array([tube.radius_at(np.linspace(s - 1.0, s + 1.0, 41)).min() for s in arcs])
    drift_x = motion.lateral * narrowest * _slow_wave(frames, rng, periods=(200.0, 600.0))
    drift_y = motion.lateral * narrowest * _slow_wave(frames, rng, periods=(200.0, 600.0))
    position = centre + drift_x[:, None] * across + drift_y[:, None] * down

    roll = np.radians(motion.roll_deg) * _slow_wave(frames, rng, periods=(300.0, 900.0))
    yaw = np.radians(motion.sway_deg) * _slow_wave(frames, rng, periods=(200.0, 600.0))
    pitch = np.radians(motion.sway_deg) * _slow_wave(frames, rng, periods=(200.0, 600.0))
    turn_yaw, turn_pitch = _turns(frames, motion, rng, scripted)
    yaw, pitch = yaw + turn_yaw, pitch + turn_pitch
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for f in range(frames):
        x = np.cos(roll[f]) * across[f] + np.sin(roll[f]) * down[f]
        y = np.cross(tangent[f], x)
        base = np.stack([x, y, tangent[f]], axis=1)
        poses[f, :3, :3] = base @ _rotation_y(yaw[f]) @ _rotation_x(pitch[f])
        poses[f, :3, 3] = position[f]
    return poses


def _turns(frames: int, motion: MotionStyle, rng: np.random.Generator,
           scripted: bool) -> tuple[np.ndarray, np.ndarray]:
    """Yaw and pitch (rad) of the deliberate turns: each swings the view by a drawn angle in a drawn direction
    over a drawn number of frames (a smooth S-curve) and stays there. A scripted sequence has one, starting within
    :data:`TEST_TURN_START`; others a Poisson count starting anywhere."""
    yaw, pitch = np.zeros(frames), np.zeros(frames)
    count = 1 if scripted else rng.poisson(motion.turns_per_100_frames * frames / 100.0)
    window = TEST_TURN_START if scripted else (0.0, 1.0)
    for _ in range(count):
        begin = rng.uniform(window[0] * frames, window[1] * frames)
        duration = rng.uniform(*motion.turn_frames)
        angle = np.radians(rng.uniform(*motion.turn_deg))
        direction = rng.uniform(0, 2 * np.pi)
        progress = np.clip((np.arange(frames) - begin) / duration, 0.0, 1.0)
        swing = angle * (0.5 - 0.5 * np.cos(np.pi * progress))
        yaw += np.cos(direction) * swing
        pitch += np.sin(direction) * swing
    return yaw, pitch


def _slow_wave(frames: int, rng: np.random.Generator, periods: tuple[float, float]) -> np.ndarray:
    """A smooth random signal in [-1, 1] over frames: two sinusoids with periods (in frames) in ``periods``."""
    period = rng.uniform(*periods, size=2)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    weight = rng.uniform(0.3, 1.0, size=2)
    f = np.arange(frames)[:, None]
    wave = (weight * np.sin(2 * np.pi * f / period + phase)).sum(axis=1)
    return wave / weight.sum()


def _smoothed_centreline(tube: Tube, start: float, stop: float, smoothing_cm: float):
    """The centreline polyline low-pass filtered (Gaussian of ``smoothing_cm``) along its arc length, as an
    interpolating function."""
    grid = np.arange(start, stop + CENTRELINE_STEP_CM, CENTRELINE_STEP_CM)
    points = tube.centreline_at(np.clip(grid, 0, tube.length))
    sigma = smoothing_cm / CENTRELINE_STEP_CM
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
