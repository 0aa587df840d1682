"""The procedural renderer: exact geometry, exact ground truth through our readers, native byte formats.

Everything runs at tiny sizes (32-64 px, a few frames) to stay fast.
"""

from __future__ import annotations

import filecmp
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from endoflow.config import ConfigError, Params
from endoflow.data.check import check_dataset
from endoflow.data.endoslam import EndoSLAMReader
from endoflow.data.scenenet import SceneNetReader, scenenet_intrinsics
from endoflow.data.simcol import SimColReader
from endoflow.geometry.pose import relative_pose
from endoflow.geometry.warp import warp_frame
from endoflow.synth.camera_path import _turns, scripted_arcs
from endoflow.synth.render import ATLAS_PAD, MAX_DEPTH_CM, pixel_rays, render_tube_frame
from endoflow.synth.rooms import Room, render_room
from endoflow.synth.scenes import STYLES, make_tube_sequence
from endoflow.synth.tube import Hits, Tube, TubeView, _exhaustive_hits, intersect, surface_points, tube_view
from endoflow.synth.writers import (
    SIMCOL_CAM_TXT,
    plan_jobs,
    room_sequence,
    scenenet_shape,
    simcol_intrinsics,
    synthesize_layout,
    synthesize_layouts,
    tube_sequence,
    unitycam_intrinsics,
)
from tests.module_temp import ModuleTemp
from tests.samples import SIMCOL_SAMPLE

SAMPLE = SIMCOL_SAMPLE / "SyntheticColon_I"
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def simcol_root(module_tmp: ModuleTemp) -> Path:
    root = module_tmp("simcol")
    synthesize_layout("simcol", root, sequences=1, frames=4, size=48, seed=3, workers=1)
    return root


@pytest.fixture(scope="module")
def endoslam_root(module_tmp: ModuleTemp) -> Path:
    root = module_tmp("endoslam")
    synthesize_layout("endoslam", root, sequences=2, frames=4, size=48, seed=3, workers=1)
    return root


@pytest.fixture(scope="module")
def scenenet_root(module_tmp: ModuleTemp) -> Path:
    root = module_tmp("scenenet")
    synthesize_layout("scenenet", root, sequences=10, frames=2, size=32, seed=3, workers=1)
    return root


# ------------------------------------------------------------------------------------------ geometry
def _straight_cylinder(radius: float, length: float, segments: int) -> Tube:
    step = length / segments
    z = np.arange(segments + 1) * step
    return Tube(
        joints=np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1),
        normals=np.tile([0.0, 0.0, 1.0], (segments + 1, 1)),
        arc=z,
        directions=np.tile([0.0, 0.0, 1.0], (segments, 1)),
        lengths=np.full(segments, step),
        radii=np.full(segments, radius),
        slopes=np.zeros(segments),
        e1=np.tile([1.0, 0.0, 0.0], (segments, 1)),
        e2=np.tile([0.0, 1.0, 0.0], (segments, 1)),
    )


def test_straight_cylinder_depth_is_the_closed_form():
    # Camera on the axis looking down it: the ray K^-1 [u, v, 1] = (x, y, 1) meets the wall at z = R / |(x, y)|,
    # unless that lies beyond the cap at the tube's end.
    radius, length = 1.5, 12.0
    tube = _straight_cylinder(radius, length, segments=40)
    origin = np.array([0.0, 0.0, 0.5])
    view = tube_view(tube, origin, 0, 40, CPU)
    K = simcol_intrinsics(32)
    rays = pixel_rays(K, 32, 32, 1, CPU)[-32 * 32 :]
    hits = intersect(view, rays)
    expected = np.minimum(radius / np.linalg.norm(rays[:, :2].numpy(), axis=1).clip(1e-9), length - 0.5)
    np.testing.assert_allclose(hits.t.numpy(), expected, rtol=1e-5, atol=1e-5)
    assert bool(((hits.slab >= 0) == torch.as_tensor(expected < length - 0.5)).all())


def _sequence(style: str, frames: int = 3, seed: int = 0):
    return make_tube_sequence(STYLES[style], frames, np.random.default_rng(seed), CPU)


def _view_from_second_frame(style: str) -> tuple[Tube, np.ndarray, TubeView, torch.Tensor]:
    """The tube, the camera centre, a 30-slab view and world-frame 40x40 pixel rays of a sequence's frame 1."""
    sequence = _sequence(style)
    tube, pose = sequence.scene.tube, sequence.poses[1]
    origin = pose[:3, 3]
    camera = tube.slab_containing(origin)
    view = tube_view(tube, origin, max(camera - 1, 0), camera + 30, CPU)
    rays = pixel_rays(simcol_intrinsics(40), 40, 40, 1, CPU) @ torch.as_tensor(pose[:3, :3].T, dtype=torch.float32)
    return tube, origin, view, rays


@pytest.mark.parametrize("style", ["SyntheticColon_I", "SyntheticColon_III", "Small Intestine"])
def test_hits_lie_on_their_slab_wall_and_fast_path_equals_exhaustive_search(style):
    tube, origin, view, rays = _view_from_second_frame(style)
    hits = intersect(view, rays)
    exhaustive_t, exhaustive_slab = _exhaustive_hits(view, rays)
    # float32 rounding: the two paths solve the same quadratics in another order, which at grazing incidence
    # moves a root by up to about 1e-4 of its depth. A ray that grazes a fold's crest ring (within rounding)
    # may pass it on one path and stop on it on the other: a silhouette pixel, rare, and only on a ring.
    differ = ~torch.isclose(hits.t, exhaustive_t, rtol=2e-4, atol=2e-4)
    assert differ.float().mean() < 2e-3
    graze = exhaustive_slab[differ] + view.first
    grazing = (rays[differ] * exhaustive_t[differ, None]).double().numpy() + origin
    along = ((grazing - tube.joints[graze]) * tube.directions[graze]).sum(1)
    on_ring = np.minimum(np.abs(along), np.abs(along - tube.lengths[graze])) < 2e-4
    assert on_ring.all(), "fast and exhaustive paths disagree away from a joint ring"

    wall = hits.slab >= 0
    assert wall.float().mean() > 0.5
    j = hits.slab[wall].numpy() + view.first
    points = (rays[wall] * hits.t[wall, None]).double().numpy() + origin
    rel = points - tube.joints[j]
    a = (rel * tube.directions[j]).sum(1)
    rho = np.linalg.norm(rel - a[:, None] * tube.directions[j], axis=1)
    np.testing.assert_allclose(rho, tube.radii[j] + tube.slopes[j] * a, atol=2e-4)
    assert ((rel * tube.normals[j]).sum(1) >= -2e-4).all()
    assert (((points - tube.joints[j + 1]) * tube.normals[j + 1]).sum(1) <= 2e-4).all()


@pytest.mark.parametrize("style", ["SyntheticColon_I", "SyntheticColon_III"])
def test_shading_normals_are_continuous_across_joint_planes_where_the_walls_crease(style):
    # Points on joint plane j belong to both slab j - 1 and slab j: both must shade them alike, although
    # the two cones' own normals there differ by the crease between them.
    tube, origin, view, rays = _view_from_second_frame(style)
    hits = intersect(view, rays)
    on_wall = hits.slab > 0
    rays, slab = rays[on_wall], hits.slab[on_wall]
    # move each hit along its ray onto the plane of its slab's first joint, where the slab before meets it
    t_plane = (view.joints[slab] * view.normals[slab]).sum(-1) / (rays * view.normals[slab]).sum(-1)
    from_here = surface_points(view, rays, Hits(t=t_plane, slab=slab))
    from_before = surface_points(view, rays, Hits(t=t_plane, slab=slab - 1))
    crease = torch.rad2deg(torch.acos((from_here.normals * from_before.normals).sum(-1).clamp(-1, 1)))
    assert crease.max() > 5.0
    np.testing.assert_allclose(from_here.shading_normals.numpy(), from_before.shading_normals.numpy(), atol=2e-5)
    np.testing.assert_allclose(from_here.along.numpy(), from_before.along.numpy(), atol=2e-5)


def test_depth_is_z_of_the_hit_in_the_camera_frame():
    sequence = _sequence("SyntheticColon_I")
    pose = sequence.poses[0]
    origin = pose[:3, 3]
    view = tube_view(sequence.scene.tube, origin, 0, len(sequence.scene.tube.lengths), CPU)
    K = simcol_intrinsics(24)
    rays = pixel_rays(K, 24, 24, 1, CPU) @ torch.as_tensor(pose[:3, :3].T, dtype=torch.float32)
    hits = intersect(view, rays)
    surface = surface_points(view, rays, hits)
    in_camera = surface.points.double().numpy() @ pose[:3, :3]
    np.testing.assert_allclose(in_camera[:, 2], hits.t.numpy(), rtol=1e-5)


@pytest.mark.parametrize("style", sorted(STYLES))
def test_every_pixel_has_a_depth_within_the_20cm_scale(style):
    sequence = _sequence(style, frames=2, seed=1)
    rgb, depth = render_tube_frame(sequence.scene, sequence.poses[-1], unitycam_intrinsics(32), 32, 32)
    assert np.isfinite(depth).all() and depth.min() > 0.1 and depth.max() <= MAX_DEPTH_CM
    assert rgb.shape == (32, 32, 3) and 0.02 < rgb.mean() < 0.9


def test_texture_wraps_around_the_tube_without_a_seam():
    sequence = _sequence("SyntheticColon_I")
    atlas = sequence.scene.atlas[0, :3]
    inner = atlas[..., ATLAS_PAD:-ATLAS_PAD]
    seam = (inner[..., 0] - inner[..., -1]).abs().mean()
    neighbours = (inner[..., 1:] - inner[..., :-1]).abs().mean()
    assert seam < 2 * neighbours


# ------------------------------------------------------------------------------------ writers, formats
def test_same_seed_same_bytes(tmp_path):
    for name in ("a", "b"):
        synthesize_layout("endoslam", tmp_path / name, sequences=1, frames=2, size=24, seed=7, workers=1)
    comparison = filecmp.dircmp(tmp_path / "a", tmp_path / "b")
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) == 5
    match, mismatch, errors = filecmp.cmpfiles(tmp_path / "a", tmp_path / "b", [str(f) for f in files], shallow=False)
    assert not mismatch and not errors and comparison.left_only == comparison.right_only == []


def test_the_stages_one_pool_writes_every_layout_as_rendering_it_alone_does(tmp_path):
    """The synthesize stage renders every layout's sequences in one pool of two processes (each imports torch once);
    the files are those one process writes for each layout on its own."""
    synth = Params().synth
    small = {"simcol": 1, "endoslam": 1, "scenenet": 2, "video": 2}
    params = Params().replace(synth=synth.replace(size=24, workers=2, **{
        layout: getattr(synth, layout).replace(sequences=count, frames=3,
                                               **({"test_frames": 3} if layout in ("simcol", "endoslam") else {}))
        for layout, count in small.items()}))
    lines = synthesize_layouts({layout: tmp_path / "pooled" / layout for layout in small}, params)
    assert [line.split(":")[0] for line in lines[:-1]] == list(small)
    assert "frames rendered in" in lines[-1] and "2 workers" in lines[-1]
    for layout in small:
        synthesize_layout(layout, tmp_path / "alone" / layout, params=params, workers=1)
    pooled, alone = (sorted(p.relative_to(tmp_path / run) for p in (tmp_path / run).rglob("*") if p.is_file())
                     for run in ("pooled", "alone"))
    assert pooled == alone and len(pooled) > 20
    assert all((tmp_path / "pooled" / f).read_bytes() == (tmp_path / "alone" / f).read_bytes() for f in pooled)


def test_simcol_layout_names(simcol_root):
    names = sorted(str(p.relative_to(simcol_root)) for p in simcol_root.rglob("*") if "Frames_" not in p.name)
    for scene, sequence in (("SyntheticColon_I", "S1"), ("SyntheticColon_II", "B1"), ("SyntheticColon_III", "O1")):
        assert f"{scene}/cam.txt" in names
        assert f"{scene}/SavedPosition_{sequence}.txt" in names
        assert f"{scene}/SavedRotationQuaternion_{sequence}.txt" in names
        frames = sorted(p.name for p in (simcol_root / scene / f"Frames_{sequence}").iterdir())
        assert frames == [f"Depth_{i:04d}.png" for i in range(4)] + [f"FrameBuffer_{i:04d}.png" for i in range(4)]
    assert not [n for n in names if Path(n).name.startswith(".")], "temporary files left behind"


def _decode(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_simcol_bytes_match_the_real_dataset(simcol_root):
    scene = simcol_root / "SyntheticColon_I"
    frame, depth = _decode(scene / "Frames_S1" / "FrameBuffer_0000.png"), _decode(scene / "Frames_S1" / "Depth_0000.png")
    assert frame.dtype == np.uint16 and frame.shape == (48, 48, 4)
    assert (frame[..., 3] == 65280).all() and (frame[..., :3] % 256 == 0).all()
    assert depth.dtype == np.uint16 and depth.ndim == 2
    assert (scene / "cam.txt").read_bytes() == SIMCOL_CAM_TXT.encode()
    positions = (scene / "SavedPosition_S1.txt").read_text().splitlines()
    rotations = (scene / "SavedRotationQuaternion_S1.txt").read_text().splitlines()
    assert len(positions) == len(rotations) == 4
    assert all(len(line.split(" ")) == 3 for line in positions) and all(len(line.split(" ")) == 4 for line in rotations)
    if not SAMPLE.is_dir():
        pytest.skip(f"real SimCol3D sample not found at {SAMPLE}")
    real_frame, real_depth = _decode(SAMPLE / "Frames_S1" / "FrameBuffer_0000.png"), _decode(SAMPLE / "Frames_S1" / "Depth_0000.png")
    assert (real_frame.dtype, real_frame.shape[2], real_frame[0, 0, 3]) == (frame.dtype, frame.shape[2], frame[0, 0, 3])
    assert (real_depth.dtype, real_depth.ndim) == (depth.dtype, depth.ndim)
    assert (scene / "cam.txt").read_bytes() == (SAMPLE / "cam.txt").read_bytes()


def test_simcol_reader_recovers_the_exact_poses_rgb_and_depth(simcol_root):
    jobs = plan_jobs("simcol", simcol_root, 1, 4, 48, 3, "cpu", Params())
    read = {s.name: s for s in SimColReader(simcol_root, Params().data.simcol).sequences()}
    assert sorted(read) == ["B1", "O1", "S1"]
    for job in jobs:
        sequence = read[job.name]
        truth = tube_sequence(job)
        np.testing.assert_allclose(sequence.poses, truth.poses, atol=1e-5)
        np.testing.assert_allclose(sequence.K, simcol_intrinsics(48), rtol=1e-9)
        rgb, depth = render_tube_frame(truth.scene, truth.poses[2], sequence.K, 48, 48)
        assert np.array_equal(sequence.load_rgb(2), np.round(rgb * 255).astype(np.uint8))
        np.testing.assert_allclose(sequence.load_depth(2), depth, atol=20 / 255 / 256)


def test_endoslam_bytes_and_reader(endoslam_root):
    organ = endoslam_root / "UnityCam" / "Small Intestine"
    depth = _decode(organ / "Pixelwise Depths" / "aov_image_0001.png")
    assert depth.dtype == np.uint8 and depth.shape == (48, 48, 4)
    assert (depth[..., 0] == depth[..., 1]).all() and (depth[..., 1] == depth[..., 2]).all() and (depth[..., 3] == 255).all()
    frame = _decode(organ / "Frames" / "image_0001.png")
    assert frame.dtype == np.uint8 and frame.shape == (48, 48, 3)
    lines = (organ / "Poses" / "intestine_position_rotation.csv").read_text().splitlines()
    assert lines[0] == "tX,tY,tZ,rX,rY,rZ,rW,time(s)" and len(lines) == 5

    jobs = {job.group: job for job in plan_jobs("endoslam", endoslam_root, 2, 4, 48, 3, "cpu", Params())}
    read = EndoSLAMReader(endoslam_root, Params().data.endoslam).sequences()
    assert sorted(s.name for s in read) == ["UnityCam/Colon", "UnityCam/Small Intestine"]
    for sequence in read:
        truth = tube_sequence(jobs[sequence.group])
        np.testing.assert_allclose(sequence.poses, truth.poses, atol=1e-5)
        np.testing.assert_allclose(sequence.K, unitycam_intrinsics(48), rtol=1e-9)
        _, expected = render_tube_frame(truth.scene, truth.poses[1], sequence.K, 48, 48)
        np.testing.assert_allclose(sequence.load_depth(1), expected, atol=20 / 255 / 2 + 1e-5)


def test_scenenet_layout_and_depth_are_ray_lengths_in_mm(scenenet_root):
    height, width = scenenet_shape(32)
    trajectory = scenenet_root / "train" / "0" / "0"
    assert sorted(p.name for p in (trajectory / "depth").iterdir()) == ["0.png", "25.png"]
    assert sorted(p.name for p in (trajectory / "photo").iterdir()) == ["0.jpg", "25.jpg"]
    assert (scenenet_root / "val" / "0" / "9").is_dir()
    depth = _decode(trajectory / "depth" / "25.png")
    assert depth.dtype == np.uint16 and depth.shape == (height, width) and depth.min() > 0
    # A bare room seen from its centre straight at the +x wall: z-depth is the distance to that wall.
    room = Room(size=np.array([400.0, 300.0, 250.0]), blocks=np.zeros((0, 2, 3)), colours=np.full((6, 3), 0.5))
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera x = -world y, y = -world z, z = world x
    pose[:3, 3] = [100.0, 150.0, 125.0]
    K = scenenet_intrinsics(height, width)
    _, length = render_room(room, pose, K, height, width, CPU)
    v, u = np.mgrid[0:height, 0:width]
    z = length / np.linalg.norm(np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1), axis=-1)
    centre = z[height // 4 : 3 * height // 4, width // 4 : 3 * width // 4]
    np.testing.assert_allclose(centre, 300.0, rtol=1e-6)
    assert len(SceneNetReader(scenenet_root, Params().data.scenenet).sequences()) == 10


# --------------------------------------------------------------------- ground truth explains the motion
def test_gt_warp_at_most_half_the_identity_error_on_simcol_and_endoslam(tmp_path):
    for layout in ("simcol", "endoslam"):
        synthesize_layout(layout, tmp_path / layout, sequences=2 if layout == "endoslam" else 1, frames=6, size=64, seed=0, workers=1)
        report = check_dataset(tmp_path / layout, layout, Params(), max_ratio=0.5)
        assert report["ok"], report
        assert len(report["sequences"]) == (2 if layout == "endoslam" else 3)
        # Also without the check's gain compensation: the light moving with the camera stays modest.
        assert all(entry["plain_ratio"] <= 0.5 for entry in report["sequences"]), report


def test_gt_warp_at_most_half_the_identity_error_on_scenenet_rooms():
    job = plan_jobs("scenenet", Path("unused"), 1, 3, 64, 0, "cpu", Params())[0]
    room, poses = room_sequence(job)
    height, width = scenenet_shape(64)
    K = scenenet_intrinsics(height, width)
    # SceneNet frames are 25 simulator frames apart; check on intermediate poses a short step apart.
    near = poses[0].copy()
    near[:3, 3] += 0.05 * (poses[1][:3, 3] - poses[0][:3, 3])
    rgb_t, length = render_room(room, poses[0], K, height, width, CPU)
    rgb_s, _ = render_room(room, near, K, height, width, CPU)
    rays = np.linalg.norm(np.linalg.inv(K) @ np.stack([*np.meshgrid(np.arange(width), np.arange(height)), np.ones((height, width))]).reshape(3, -1), axis=0)
    depth = torch.as_tensor(length.reshape(-1) / rays, dtype=torch.float32).reshape(1, 1, height, width)
    image_s = torch.as_tensor(rgb_s).permute(2, 0, 1)[None]
    image_t = torch.as_tensor(rgb_t).permute(2, 0, 1)[None]
    T = torch.as_tensor(relative_pose(near, poses[0]), dtype=torch.float32)[None]
    warped, valid = warp_frame(image_s, depth, T, torch.as_tensor(K, dtype=torch.float32)[None])
    mask = valid.float()
    gt = ((warped - image_t).abs() * mask).sum() / mask.sum()
    identity = ((image_s - image_t).abs() * mask).sum() / mask.sum()
    assert gt <= 0.5 * identity


def test_more_unitycam_sequences_than_organs_is_refused_naming_the_key(tmp_path: Path) -> None:
    from endoflow.config import ConfigError

    with pytest.raises(ConfigError, match="synth.endoslam.sequences must be at most 3"):
        plan_jobs("endoslam", tmp_path, 4, 4, 48, 3, "cpu", Params())


def test_the_preview_shows_the_real_sample_as_read_by_the_simcol_reader():
    if not SAMPLE.is_dir():
        pytest.skip(f"real SimCol3D sample not found at {SAMPLE}")
    from endoflow.synth.preview import real_simcol_row

    title, images, depths, unit = real_simcol_row(SAMPLE.parent)
    assert title == "real SimCol3D SyntheticColon_I S1" and unit == "z-depth, cm"
    assert [image.shape for image in images] == [(475, 475, 3)] * 2
    assert all(0 <= image.min() and image.max() <= 1 for image in images)
    # the sample's README: depth from 0.63 to 13.3 cm in these frames
    assert all(0.6 < depth.min() and depth.max() < 13.4 for depth in depths)


def test_the_preview_names_a_folder_that_is_no_simcol3d_root(tmp_path, monkeypatch, capsys):
    from endoflow.synth import preview

    monkeypatch.setattr("sys.argv", ["preview", str(tmp_path / "picture.png"), "--real", str(tmp_path)])
    with pytest.raises(SystemExit) as stop:
        preview.main()
    assert stop.value.code == 2
    assert f"--real: {tmp_path}: no SimCol3D scene folder found" in capsys.readouterr().err
    assert not (tmp_path / "picture.png").exists()


def test_test_sequences_follow_the_script_and_others_their_random_phases():
    params = Params()
    jobs = {job.name: job for job in plan_jobs("simcol", Path("unused"), 15, 60, 48, 0, "cpu", params,
                                               test_frames=120)}
    for name, job in jobs.items():
        test = name in params.data.simcol.test
        assert (job.scripted, job.frames) == ((True, 120) if test else (False, 60))
    endoslam = plan_jobs("endoslam", Path("unused"), 2, 40, 48, 0, "cpu", params, test_frames=90)
    assert all(job.scripted and job.frames == 90 for job in endoslam)  # data.endoslam.split is test


def _forward_steps(poses: np.ndarray) -> np.ndarray:
    """Each frame's motion along its own optical axis, cm (positive: advancing)."""
    return np.array([relative_pose(a, b)[2, 3] for a, b in zip(poses[:-1], poses[1:])])


# The last pose of the first unscripted SimCol3D and video sequence (seed 0, 60 frames), recorded at commit c3ada67,
# before synth.phase_frames existed: camera position (cm) and viewing direction in the world frame.
DEFAULT_LAST_POSES = {"simcol": ([-32.7580415782, -26.5803382864, -27.7904777928], [0.5417867432, 0.7657569902,
                                                                                      0.3465304559]),
                      "video": ([35.6824815953, -32.1861475737, -21.8417164888], [0.0029813349, 0.3585230522,
                                                                                  0.9335161127])}


def test_the_default_phases_draw_the_paths_they_drew_before_the_key_existed():
    for layout, (position, direction) in DEFAULT_LAST_POSES.items():
        job = next(job for job in plan_jobs(layout, Path("unused"), 2, 60, 16, 0, "cpu", Params(), test_frames=120)
                   if not job.scripted)
        last = tube_sequence(job).poses[-1]
        np.testing.assert_allclose(last[:3, 3], position, atol=1e-6)
        np.testing.assert_allclose(last[:3, 2], direction, atol=1e-8)


def test_shorter_phases_make_training_sequences_cross_phases_and_leave_test_sequences_as_they_were():
    """synth.phase_frames: the default training sequences mostly advance (the data asks for one step); shorter
    phases make each one pause or withdraw as well. The scripted test sequences keep their paths to the bit."""
    default = Params()
    short = default.replace(synth=default.synth.replace(phase_frames=[10, 20]))
    default_jobs, short_jobs = (plan_jobs("simcol", Path("unused"), 2, 60, 16, 0, "cpu", params, test_frames=120)
                                for params in (default, short))
    assert all(job.phase_frames is None for job in default_jobs)
    assert all(job.phase_frames == (10, 20) for job in short_jobs)
    held_back = {"default": [], "short": []}  # per training sequence: the share of frames pausing or withdrawing
    for before, after in zip(default_jobs, short_jobs):
        paths = {"default": tube_sequence(before).poses, "short": tube_sequence(after).poses}
        if before.scripted:
            np.testing.assert_array_equal(paths["default"], paths["short"])
            continue
        slowest = STYLES[before.group].motion.speed[0]
        for name, poses in paths.items():
            held_back[name].append(np.mean(_forward_steps(poses) < 0.5 * slowest))
    assert len(held_back["short"]) == 4  # S1, S2, B1, B2; O1 and O2 are test sequences
    assert np.mean(held_back["short"]) > 0.2
    assert np.mean(held_back["short"]) > 2 * np.mean(held_back["default"])


def test_a_phase_range_longest_first_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"synth.phase_frames must be \[shortest, longest\]"):
        Params().synth.replace(phase_frames=[30, 10])
    with pytest.raises(ConfigError, match="synth.phase_frames"):
        Params().synth.replace(phase_frames=[0, 10])
    with pytest.raises(ConfigError, match="synth.phase_frames"):
        Params().synth.replace(phase_frames=[10])


def test_a_scripted_camera_crosses_every_change_of_motion():
    """A slow advance, a pause, a withdrawal, a fast advance (each about a quarter), and one turn: what a path that
    repeats one step cannot follow. Signed speeds along the path from the arc lengths, per quarter."""
    motion = STYLES["SyntheticColon_I"].motion
    for seed in range(5):
        arcs = scripted_arcs(120, motion, 4.0, np.random.default_rng(seed))
        speed = np.diff(arcs)
        # the middle of each phase (ramps spread changes over camera_path.RAMP_FRAMES)
        slow, pause, withdraw, fast = (np.median(speed[int(a * 119):int(b * 119)])
                                       for a, b in ((0.05, 0.18), (0.32, 0.42), (0.58, 0.68), (0.85, 0.97)))
        assert slow == pytest.approx(motion.speed[0], rel=0.05)
        assert abs(pause) < 0.01 * motion.speed[0]
        assert withdraw == pytest.approx(-np.mean(motion.speed), rel=0.05)
        assert fast == pytest.approx(motion.speed[1], rel=0.05)
        assert arcs.min() >= 4.0
        yaw, pitch = _turns(120, motion, np.random.default_rng(seed), scripted=True)
        swing = np.hypot(yaw, pitch)
        started = np.flatnonzero(swing > 0)[0]
        assert 0.3 * 120 - 1 <= started <= 0.6 * 120 + 1
        assert np.degrees(swing[-1]) >= motion.turn_deg[0] - 1e-9


# ------------------------------------------------------------------------------------------ the second look
def test_the_second_look_shows_the_same_scenes_through_another_camera_and_its_ground_truth_holds(tmp_path):
    """synth.look: second keeps the scenes and paths, changes what real footage differs in (colour, light, a circular
    field of view, a shorter focal length); its ground truth still explains the motion."""
    from endoflow.config import params_from_dict
    from endoflow.synth.scenes import SECOND_LOOK_FOCAL

    second = params_from_dict({"synth": {"look": "second"}})
    synthesize_layout("simcol", tmp_path / "built-in", sequences=1, frames=6, size=64, seed=0, workers=1)
    synthesize_layout("simcol", tmp_path / "second", sequences=1, frames=6, size=64, seed=0, workers=1, params=second)
    built_in, looked = (SimColReader(tmp_path / look, Params().data.simcol).sequences() for look in ("built-in", "second"))
    for a, b in zip(built_in, looked):
        np.testing.assert_allclose(b.poses, a.poses)  # the same paths
        np.testing.assert_allclose(b.K[[0, 1], [0, 1]], SECOND_LOOK_FOCAL * a.K[[0, 1], [0, 1]])
        rgb = b.load_rgb(2)
        assert not rgb[0, 0].any() and not rgb[-1, -1].any() and rgb[32, 32].any()  # black corners, a scene inside
        assert np.abs(rgb.astype(float) - a.load_rgb(2)).mean() > 20  # another look
    report = check_dataset(tmp_path / "second", "simcol", Params(), max_ratio=0.5)
    assert report["ok"], report
