"""Scene presets (shape, motion, mucosa, light) and the sequence generator shared by the tube layouts.

See docs/synthetic_data.md, "Camera, light and mucosa" (scenes).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from endoflow.geometry.pose import quaternion_xyzw_to_matrix
from endoflow.synth.camera_path import MotionStyle, camera_poses, scripted_arcs, trajectory_arcs
from endoflow.synth.render import LightStyle, TubeScene, make_scene
from endoflow.synth.texture import MucosaStyle, bump_slopes, mucosa_atlas
from endoflow.synth.tube import TubeShape, build_tube

TEXEL_CM = 0.025  # atlas resolution on the wall (about a pixel at 2 cm in a 128-px frame)
VIEW_AHEAD_CM = 22.0  # tube length built beyond the last camera position
LEAD_IN_CM = 4.0  # tube length behind the first camera position


@dataclass
class SceneStyle:
    shape: TubeShape
    motion: MotionStyle
    mucosa: MucosaStyle
    light: LightStyle


_COLON = TubeShape(
    radius=(1.5, 2.6),
    radius_wavelength=14.0,
    fold_period=(2.0, 3.2),
    fold_depth=(0.1, 0.25),
    fold_width=1.5,
    curvature=0.3,
    bend_spacing=0.35,
)
# calibrated on real SimCol3D poses (camera_path.py, docs/synthetic_data.md): ~1.35 mm and ~0.1 degree per frame
_COLON_MOTION = MotionStyle(speed=(0.1, 0.17), phase_shares=(0.6, 0.25, 0.15), phase_frames=(30, 120), lateral=0.25,
                            sway_deg=1.5, roll_deg=6.0, turn_deg=(4.0, 10.0), turn_frames=(30, 60),
                            turns_per_100_frames=0.5)
_LIGHT = LightStyle(exposure=12.0, diffuse=1.0, specular=0.08, shininess=40.0, vignetting=1.0, ambient=0.002)

STYLES: dict[str, SceneStyle] = {
    "SyntheticColon_I": SceneStyle(
        shape=_COLON,
        motion=_COLON_MOTION,
        mucosa=MucosaStyle(
            base=(0.95, 0.58, 0.32),
            mottle=(0.88, 0.45, 0.28),
            vessel=(0.65, 0.22, 0.15),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.5,
            vessel_strength=0.55,
            grain=0.15,
        ),
        light=_LIGHT,
    ),
    "SyntheticColon_II": SceneStyle(
        shape=_COLON,
        motion=_COLON_MOTION,
        mucosa=MucosaStyle(
            base=(0.90, 0.50, 0.42),
            mottle=(0.95, 0.66, 0.52),
            vessel=(0.55, 0.16, 0.18),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.6,
            vessel_strength=0.55,
            grain=0.15,
        ),
        light=LightStyle(exposure=6.0, diffuse=1.0, specular=0.2, shininess=50.0, vignetting=1.5, ambient=0.002),
    ),
    "SyntheticColon_III": SceneStyle(
        shape=TubeShape(
            radius=(1.2, 2.0),
            radius_wavelength=9.0,
            fold_period=(1.4, 2.2),
            fold_depth=(0.3, 0.45),
            fold_width=0.55,
            curvature=0.16,
            bend_spacing=0.35,
        ),
        motion=_COLON_MOTION,
        mucosa=MucosaStyle(
            base=(0.92, 0.68, 0.50),
            mottle=(0.80, 0.50, 0.40),
            vessel=(0.70, 0.25, 0.20),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.45,
            vessel_strength=0.55,
            grain=0.15,
        ),
        light=LightStyle(exposure=5.0, diffuse=1.0, specular=0.08, shininess=40.0, vignetting=1.0, ambient=0.002),
    ),
    "Colon": SceneStyle(
        shape=TubeShape(
            radius=(1.1, 1.5),
            radius_wavelength=10.0,
            fold_period=(1.5, 2.4),
            fold_depth=(0.15, 0.3),
            fold_width=0.5,
            curvature=0.15,
            bend_spacing=0.35,
        ),
        motion=replace(_COLON_MOTION, speed=(0.1, 0.16)),
        mucosa=MucosaStyle(
            base=(0.88, 0.45, 0.38),
            mottle=(0.78, 0.35, 0.30),
            vessel=(0.55, 0.12, 0.12),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.5,
            vessel_strength=0.75,
            grain=0.15,
        ),
        light=LightStyle(exposure=4.0, diffuse=1.0, specular=0.2, shininess=60.0, vignetting=1.5, ambient=0.002),
    ),
    "Small Intestine": SceneStyle(
        shape=TubeShape(
            radius=(0.8, 1.2),
            radius_wavelength=8.0,
            fold_period=(0.7, 1.1),
            fold_depth=(0.15, 0.3),
            fold_width=0.35,
            curvature=0.2,
            bend_spacing=0.2,
        ),
        motion=replace(_COLON_MOTION, speed=(0.08, 0.14)),
        mucosa=MucosaStyle(
            base=(0.90, 0.55, 0.45),
            mottle=(0.95, 0.70, 0.55),
            vessel=(0.60, 0.18, 0.16),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.8,
            vessel_strength=0.75,
            grain=0.15,
        ),
        light=LightStyle(exposure=2.5, diffuse=1.0, specular=0.2, shininess=60.0, vignetting=1.5, ambient=0.002),
    ),
    "Stomach": SceneStyle(
        shape=TubeShape(
            radius=(3.0, 4.0),
            radius_wavelength=12.0,
            fold_period=(1.5, 2.5),
            fold_depth=(0.06, 0.12),
            fold_width=0.8,
            curvature=0.06,
            bend_spacing=0.5,
        ),
        motion=replace(_COLON_MOTION, speed=(0.1, 0.17), lateral=0.3),
        mucosa=MucosaStyle(
            base=(0.90, 0.52, 0.45),
            mottle=(0.80, 0.40, 0.36),
            vessel=(0.60, 0.16, 0.15),
            mottle_strength=0.9,
            vessel_trees_per_cm2=0.4,
            vessel_strength=0.75,
            grain=0.15,
        ),
        light=LightStyle(exposure=12.0, diffuse=1.0, specular=0.2, shininess=40.0, vignetting=1.5, ambient=0.002),
    ),
}


# The renderer's second look (synth.look: second): what real footage differs in from the built-in look, to measure
# adaptation with exact ground truth. The scenes' shapes and paths are the built-in ones (the same random draws).
SECOND_LOOK_MUCOSA = dict(base=(0.86, 0.72, 0.52), mottle=(0.74, 0.56, 0.40), vessel=(0.45, 0.10, 0.14),
                          vessel_strength=0.85, grain=0.3)
SECOND_LOOK_LIGHT = dict(specular=0.9, shininess=120.0, vignetting=3.0)
SECOND_LOOK_EXPOSURE = 0.6  # times the built-in exposure
SECOND_LOOK_FOCAL = 0.75  # times the built-in focal lengths: a wider view
SECOND_LOOK_CIRCLE = 1.1  # the field of view: a circle 1.1 times the frame's side (black corners)


def second_look(style: SceneStyle) -> SceneStyle:
    """``style`` in the renderer's second look: its mucosa recoloured and grainier, its light darker towards the
    corners with strong, sharp highlights."""
    return replace(style, mucosa=replace(style.mucosa, **SECOND_LOOK_MUCOSA),
                   light=replace(style.light, exposure=style.light.exposure * SECOND_LOOK_EXPOSURE,
                                 **SECOND_LOOK_LIGHT))


@dataclass
class TubeSequence:
    scene: TubeScene
    poses: np.ndarray  # [F, 4, 4] T_world_cam, OpenCV, cm


def make_tube_sequence(style: SceneStyle, frames: int, rng: np.random.Generator, device: torch.device,
                       scripted: bool = False) -> TubeSequence:
    """A random tube, texture and camera trajectory for ``frames`` frames, placed at a random world pose; a
    ``scripted`` (test) sequence's camera follows :data:`~endoflow.synth.camera_path.TEST_SCRIPT`."""
    arcs = (scripted_arcs if scripted else trajectory_arcs)(frames, style.motion, LEAD_IN_CM, rng)
    tube = build_tube(style.shape, float(arcs.max()) + VIEW_AHEAD_CM, rng)
    poses = camera_poses(tube, arcs, style.motion, rng, scripted)
    width = 8 * int(round(2 * np.pi * np.mean(style.shape.radius) / TEXEL_CM / 8))
    texel_cm = 2 * np.pi * np.mean(style.shape.radius) / width
    # Rows for the whole wall profile, plus the cap's disc (textured as the wall continued inwards).
    rows = int(np.ceil((tube.wall_arc[-1] + tube.radii.max()) / texel_cm)) + 1
    albedo = mucosa_atlas(style.mucosa, rows, width, texel_cm, rng)
    slopes = bump_slopes(rows, width, texel_cm, style.mucosa.bump_cm, rng)
    atlas = np.concatenate([albedo, slopes], axis=-1)
    # An arbitrary world frame (as in the real data), so that readers and checks see general poses.
    rotation = quaternion_xyzw_to_matrix(rng.standard_normal(4))
    translation = rng.uniform(-40.0, 40.0, size=3)
    tube = tube.transformed(rotation, translation)
    moved = poses.copy()
    moved[:, :3, :3] = rotation @ poses[:, :3, :3]
    moved[:, :3, 3] = poses[:, :3, 3] @ rotation.T + translation
    return TubeSequence(scene=make_scene(tube, atlas, texel_cm, style.light, device), poses=moved)
