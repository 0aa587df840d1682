"""The tracker's per-pixel work on a CPU as compiled loops (numba): ``direct_alignment``'s costs of candidate states
and the Jacobian rows of its Gauss-Newton normal equations, each in one pass over the keyframe points.

Why loops: on a CPU the tensor code makes some thirty passes over the points for one state (move, project, sample
four channels and six gradients bilinearly, residual, Huber, the Jacobian's 27 rows), each writing a temporary, at
memory speed. A loop visits each point once and keeps the rest in registers. On a GPU the tensor code is the fast
one and stays.

The tensor code's arithmetic, in another order and partly wider: a point's move and projection are float32, as
there; its bilinear weights are taken from its pixel directly (the tensor code goes through ``grid_sample``'s
normalised grid and back) and are float64 (numba widens a float32 less an integer), and with them the samples,
residuals, costs and rows, rounded to float32 where they are written; the rows carry the root of their Huber weight
(the tensor code weights one side of the product). So the figures agree to float32 rounding, not to the bit
(``tests/test_direct_alignment.py``). The loops run in the calling thread (``endoflow/compiled.py``): split over
two threads beside torch's, they gained 4 % at 480 px and took 1.7 times as long at 64 px
(``benchmarks/bench_tracker.py`` with a trained model's depth).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from endoflow.compiled import compiled_loop, compiled_part

JACOBIAN_ROWS = 8  # (omega, t, log-gain, offset)
# a frame point takes part where the share of its four pixels that are well exposed, sampled bilinearly, is above
# this (all four, but those it does not touch); direct_alignment's tensor code compares with it too
WELL_EXPOSED = np.float32(0.999)


class LevelArrays(NamedTuple):
    """One pyramid level as the loops read it, all float32 but ``usable``."""

    points: np.ndarray  # [3, N] keyframe-camera points
    key_values: np.ndarray  # [3, N] their colours
    usable: np.ndarray  # [N] bool: with depth, neither saturated nor black
    frame: np.ndarray  # [4, H, W] the frame's colours and where it is well exposed
    gradients: np.ndarray  # [6, H, W] the frame's horizontal, then vertical gradients
    K: np.ndarray  # [3, 3]
    distance: np.ndarray  # [N] the points' distance from the keyframe's camera: read with a light fall-off alone
    rows: np.ndarray  # [3 U, 9] room for the weighted Jacobian row and residual of each channel of the U usable points


def state_costs(level: LevelArrays, states: np.ndarray, huber: float, falloff: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per point, for each of ``states [B, 15]`` (float32: ``[R | t]`` row-major, the gain, the offset and the
    rotation prior's cost per pixel, as ``direct_alignment`` packs them): its Huber cost summed over the channels
    plus the prior's share ``[B, N]`` float32 (0 where it does not take part), and whether it takes part ``[B, N]``
    (usable, lands inside one pixel from the border, in front, among well-exposed frame pixels)."""
    costs = np.zeros((len(states), level.points.shape[1]), np.float32)
    part = np.zeros((len(states), level.points.shape[1]), np.bool_)
    _each_point(*level, states, np.float32(huber), np.float32(falloff), False, costs, part)
    return costs, part


def normal_equations(level: LevelArrays, state: np.ndarray, huber: float, falloff: float
                     ) -> tuple[torch.Tensor, int]:
    """The Gauss-Newton system at ``state [15]`` over the points taking part (as :func:`state_costs` finds them) and
    their three channels: ``[8, 9]`` float64, the Huber-weighted ``J^T J`` in (omega, t, log-gain, offset) beside
    ``J^T r``; and how many points took part.

    The loop writes each channel's Jacobian row and residual, times the root of its Huber weight, into
    ``level.rows``, and torch's matrix product sums them. (A loop that summed the 72 products of each row itself took
    20.0 ms on a 480 px level, against 13.1 for the tensor code's whole linearisation in the same run:
    docs/benchmarks.md.)"""
    taking_part = _each_point(*level, state[None], np.float32(huber), np.float32(falloff), True,
                              np.empty((0, 0), np.float32), np.empty((0, 0), np.bool_))
    written = torch.from_numpy(level.rows[:3 * taking_part])
    return (written[:, :JACOBIAN_ROWS].T @ written).double(), int(taking_part)


@compiled_loop
def _moved_pixel(points, n, state, K, width, height):  # pragma: no cover (compiled)
    """Point ``n`` moved by ``state``'s ``[R | t]`` and projected: its coordinates, pixel ``u, v`` and whether it
    lands in front of the camera and inside, one pixel from the border (so all four pixels around it exist)."""
    px, py, pz = points[0, n], points[1, n], points[2, n]
    x = state[0] * px + state[1] * py + state[2] * pz + state[3]
    y = state[4] * px + state[5] * py + state[6] * pz + state[7]
    z = state[8] * px + state[9] * py + state[10] * pz + state[11]
    depth = max(z, np.float32(1e-9))
    u = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / depth
    v = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / depth
    inside = z > np.float32(1e-6) and u >= 1 and u <= width - 2 and v >= 1 and v <= height - 2
    return x, y, z, u, v, inside


@compiled_loop
def _corner(u, v):  # pragma: no cover (compiled)
    """The pixel above and left of ``u, v`` and the four bilinear weights of it and its neighbours (right, below,
    below right)."""
    left, top = int(np.floor(u)), int(np.floor(v))
    a, c = u - left, v - top  # float64: numba widens a float32 less an integer
    return left, top, (1 - a) * (1 - c), a * (1 - c), (1 - a) * c, a * c


@compiled_loop
def _bilinear(image, channel, corner):  # pragma: no cover (compiled)
    """``image[channel]`` sampled at a point's :func:`_corner`."""
    left, top, w00, w01, w10, w11 = corner
    return (w00 * image[channel, top, left] + w01 * image[channel, top, left + 1]
            + w10 * image[channel, top + 1, left] + w11 * image[channel, top + 1, left + 1])


@compiled_loop
def _landing(points, usable, state, K, frame, n):  # pragma: no cover (compiled)
    """Whether point ``n`` is usable and lands inside the frame in front of it at ``state``; the point moved and
    its pixel (:func:`_moved_pixel`)."""
    x, y, z, u, v, inside = _moved_pixel(points, n, state, K, frame.shape[2], frame.shape[1])
    return usable[n] and inside, x, y, z, u, v


@compiled_loop
def _lit(x, y, z, distance, n, falloff):  # pragma: no cover (compiled)
    """The factor that brings the frame's brightness at point ``n`` (moved to ``x, y, z``) to the keyframe's light:
    (distance in the frame / in the keyframe) ^ falloff; 1 without a fall-off (``distance`` then unread)."""
    if falloff == 0:
        return np.float32(1)
    return (max(np.sqrt(x * x + y * y + z * z), np.float32(1e-9)) / distance[n]) ** falloff


@compiled_loop
def _each_point(points, key_values, usable, frame, gradients, K, distance, rows, states, huber, falloff, linearise,
                costs, part):  # pragma: no cover (compiled)
    """At each of ``states``, each point taking part: its cost and that it takes part into ``costs`` and ``part``
    [B, N], or, to ``linearise`` at one state (``rows`` holds three rows for each usable point, no more), its
    weighted rows written one after the other into ``rows``; how many points took part (in all states)."""
    taking_part = 0
    for b in range(len(states)):
        state = states[b]
        gain, offset = state[12], state[13]
        for n in range(points.shape[1]):
            landing, x, y, z, u, v = _landing(points, usable, state, K, frame, n)
            if not landing:
                continue
            corner = _corner(u, v)
            if not _bilinear(frame, 3, corner) > WELL_EXPOSED:
                continue
            lit_gain = gain * _lit(x, y, z, distance, n, falloff)
            if linearise:
                _write_rows(rows, 3 * taking_part, key_values, frame, gradients, K, n, x, y, z, u, v, corner,
                            lit_gain, offset, huber, falloff)
            else:
                costs[b, n] = _cost(key_values, frame, n, corner, lit_gain, offset, huber) + state[14]
                part[b, n] = True
            taking_part += 1
    return taking_part


@compiled_part
def _cost(key_values, frame, n, corner, lit_gain, offset, huber):  # pragma: no cover (compiled)
    """Point ``n``'s Huber cost summed over the channels, the frame sampled at ``corner``."""
    cost = np.float32(0)
    for channel in range(3):
        absolute = abs(lit_gain * _bilinear(frame, channel, corner) + offset - key_values[channel, n])
        least = min(absolute, huber)
        cost += least * (absolute - np.float32(0.5) * least)
    return cost


@compiled_part
def _write_rows(rows, first, key_values, frame, gradients, K, n, x, y, z, u, v, corner, lit_gain, offset, huber,
                falloff):  # pragma: no cover (compiled)
    """Point ``n``'s Jacobian row and residual of each channel, times the root of its Huber weight, into ``rows``
    from row ``first``; the point moved to ``x, y, z`` lands at pixel ``u, v`` (``corner``)."""
    # d u / d X and d v / d X
    inverse_z = np.float32(1) / z
    du0, du1, du2 = ((K[0, 0] - u * K[2, 0]) * inverse_z, (K[0, 1] - u * K[2, 1]) * inverse_z,
                     (K[0, 2] - u * K[2, 2]) * inverse_z)
    dv0, dv1, dv2 = ((K[1, 0] - v * K[2, 0]) * inverse_z, (K[1, 1] - v * K[2, 1]) * inverse_z,
                     (K[1, 2] - v * K[2, 2]) * inverse_z)
    squared = max(x * x + y * y + z * z, np.float32(1e-18))
    for channel in range(3):
        value = _bilinear(frame, channel, corner)
        gx, gy = _bilinear(gradients, channel, corner), _bilinear(gradients, channel + 3, corner)
        # d image / d X, the light's factor growing with |X|
        dx, dy, dz = gx * du0 + gy * dv0, gx * du1 + gy * dv1, gx * du2 + gy * dv2
        if falloff != 0:
            dx += value * (falloff * x / squared)
            dy += value * (falloff * y / squared)
            dz += value * (falloff * z / squared)
        dx, dy, dz = lit_gain * dx, lit_gain * dy, lit_gain * dz
        residual = lit_gain * value + offset - key_values[channel, n]
        # the root of Huber's weight: 1 up to the threshold, threshold / |r| beyond
        root = np.sqrt(huber / max(abs(residual), huber))
        row = rows[first + channel]
        # d X / d omega = -[X]_x: d image / d omega = X x (d image / d X)
        row[0], row[1], row[2] = root * (y * dz - z * dy), root * (z * dx - x * dz), root * (x * dy - y * dx)
        row[3], row[4], row[5] = root * dx, root * dy, root * dz
        row[6], row[7], row[8] = root * (lit_gain * value), root, root * residual
