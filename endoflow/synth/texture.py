"""Procedural mucosa: a texture atlas in (arc length, angle) coordinates of the tube wall.

Rows follow the arc length, columns the angle (periodic); values are linear-light albedo in [0, 1]. See
docs/synthetic_data.md, "Camera, light and mucosa".
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

GAMMA = 2.2


@dataclass
class MucosaStyle:
    base: tuple[float, float, float]  # sRGB in [0, 1]
    mottle: tuple[float, float, float]  # second colour blended in by large-scale noise
    vessel: tuple[float, float, float]
    mottle_strength: float
    vessel_trees_per_cm2: float
    vessel_strength: float
    grain: float  # relative amplitude of the fine grain
    bump_cm: float = 0.08  # height of the lumps that tilt the shading normals


def mucosa_atlas(style: MucosaStyle, rows: int, width: int, texel_cm: float, rng: np.random.Generator) -> np.ndarray:
    """``[rows, width, 3]`` float32 linear albedo, periodic along the width; texels about ``texel_cm`` wide."""
    base = _linear(style.base)
    mottle = _linear(style.mottle)
    vessel = _linear(style.vessel)
    blotches = 0.5 + 0.5 * np.tanh(1.5 * _fractal_noise(rows, width, rng, cells=(96, 48, 24)))
    albedo = base + style.mottle_strength * blotches[..., None] * (mottle - base)
    shade = 1.0 + 0.2 * _fractal_noise(rows, width, rng, cells=(24, 10, 5))
    albedo = albedo * shade[..., None]
    trees = max(1, int(round(style.vessel_trees_per_cm2 * rows * width * texel_cm**2)))
    vessels = style.vessel_strength * _vessel_map(rows, width, trees, rng)
    albedo = albedo + vessels[..., None] * (vessel - albedo)
    grain = 1.0 + style.grain * _fractal_noise(rows, width, rng, cells=(4, 3))
    albedo = albedo * grain[..., None]
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)


def bump_slopes(rows: int, width: int, texel_cm: float, amplitude_cm: float, rng: np.random.Generator) -> np.ndarray:
    """``[rows, width, 2]`` float32 slopes (d height / d arc, d height / d around; cm per cm) of a lumpy
    height field about ``amplitude_cm`` high with lumps of about 1 cm; used to tilt shading normals."""
    lump = max(2, int(round(1.0 / texel_cm)))
    height = amplitude_cm * _fractal_noise(rows, width, rng, cells=(2 * lump, lump, lump // 2 + 1))
    along = np.gradient(height, texel_cm, axis=0)
    around = np.gradient(np.concatenate([height[:, -1:], height, height[:, :1]], axis=1), texel_cm, axis=1)[:, 1:-1]
    return np.stack([along, around], axis=-1).astype(np.float32)


def _linear(srgb: tuple[float, float, float]) -> np.ndarray:
    return np.asarray(srgb, dtype=np.float64) ** GAMMA


def _periodic_noise(rows: int, width: int, cell: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise (unit variance before smoothing) with features ``cell`` texels wide, periodic in width."""
    grid_cols = max(1, width // cell)
    grid_rows = max(2, rows // cell + 2)
    grid = rng.standard_normal((grid_rows, grid_cols)).astype(np.float32)
    tiled = np.concatenate([grid, grid, grid], axis=1)
    # Upsampling three copies and keeping the middle one makes the result wrap around seamlessly.
    up = cv2.resize(tiled, (3 * width, grid_rows * cell), interpolation=cv2.INTER_CUBIC)
    return up[:rows, width : 2 * width]


def _fractal_noise(rows: int, width: int, rng: np.random.Generator, cells: tuple[int, ...]) -> np.ndarray:
    total = np.zeros((rows, width), dtype=np.float32)
    weight = 1.0
    norm = 0.0
    for cell in cells:
        total += weight * _periodic_noise(rows, width, cell, rng)
        norm += weight * weight
        weight *= 0.6
    return total / np.sqrt(norm)


def _vessel_map(rows: int, width: int, trees: int, rng: np.random.Generator) -> np.ndarray:
    """Vessel opacity in [0, 1]: forking random walks, drawn on three side-by-side copies and folded."""
    canvas = np.zeros((rows, 3 * width), dtype=np.uint8)
    for _ in range(trees):
        stack = [(rng.uniform(width, 2 * width), rng.uniform(0, rows), rng.uniform(0, 2 * np.pi), 3.0, 200.0)]
        while stack:
            x, y, heading, thickness, ink = stack.pop()
            steps = int(rng.integers(15, 45))
            headings = heading + np.cumsum(rng.normal(0, 0.25, size=steps))
            lengths = rng.uniform(3.0, 6.0, size=steps)
            xs = x + np.concatenate([[0.0], np.cumsum(lengths * np.cos(headings))])
            ys = y + np.concatenate([[0.0], np.cumsum(lengths * np.sin(headings))])
            polyline = np.round(np.stack([xs, ys], axis=1) * 16).astype(np.int32)  # 4 fractional bits
            cv2.polylines(canvas, [polyline], False, int(ink), max(1, int(round(thickness))), cv2.LINE_AA, 4)
            if thickness * 0.7 >= 1.0:
                for step in np.nonzero(rng.random(steps) < 0.07)[0][:3]:
                    side = rng.choice([-1.0, 1.0])
                    turn = side * rng.uniform(0.4, 1.0)
                    stack.append((xs[step + 1], ys[step + 1], headings[step] + turn, thickness * 0.7, ink * 0.8))
    folded = np.maximum(np.maximum(canvas[:, :width], canvas[:, width : 2 * width]), canvas[:, 2 * width :])
    return cv2.GaussianBlur(folded.astype(np.float32) / 255.0, (0, 0), 0.8)
