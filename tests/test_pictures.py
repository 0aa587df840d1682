"""Pictures of a reconstruction: the sampler keeps a few evenly spaced frames of a stream of any length in bounded
memory; the MP4 shows each frame beside its depth, one video frame per input frame; the contact sheet is a PNG
with the frames, the path from the top and the side (beside the ground truth's where there is one), and the surface
seen by a z-buffered splat whose nearest point wins, each depth picture with a colour bar in cm; the depth preview
is TURBO of inverse depth over the model's range."""

from __future__ import annotations

import math
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from matplotlib.figure import Figure

from endoflow.reconstruction import pictures
from endoflow.reconstruction.pictures import (
    BACKGROUND,
    DEFAULT_FPS,
    GROUND_TRUTH_LABEL,
    FrameSampler,
    SideBySideVideo,
    contact_sheet,
    depth_preview,
    draw_path_side,
    draw_path_top,
    nearest_points,
    overview_camera,
    splat_footprint,
    splat_points,
    write_contact_sheet,
)

SIZE = 64
PREVIEW_RANGE_CM = (1.0, 20.0)  # the depth range of gradient_preview's colours


def gradient_rgb(height: int = SIZE, width: int = SIZE) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u * 255 // width, v * 255 // height, np.full_like(u, 128)], axis=-1).astype(np.uint8)


def gradient_preview(height: int = SIZE, width: int = SIZE) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width]
    return depth_preview((2.0 + 0.1 * u + 0.05 * v).astype(np.float32), *PREVIEW_RANGE_CM)


def pose(rotation: np.ndarray = np.eye(3), translation: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotation, translation
    return T


def yaw(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def tube(points: int, length_cm: float = 20.0, radius_cm: float = 2.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on a cylinder along +z ahead of the origin, coloured by angle."""
    rng = np.random.default_rng(seed)
    along, angle = rng.uniform(1.0, 1.0 + length_cm, points), rng.uniform(0, 2 * np.pi, points)
    vertices = np.stack([radius_cm * np.cos(angle), radius_cm * np.sin(angle), along], axis=1)
    colours = np.stack([127 + 127 * np.cos(angle), 127 + 127 * np.sin(angle), np.full(points, 90)], axis=1)
    return vertices, colours.astype(np.uint8)


def path_along_z(count: int) -> np.ndarray:
    return np.stack([pose(yaw(0.2 * math.sin(i / 5)), (math.sin(i / 7), 0.1 * i, 0.5 * i)) for i in range(count)])


# ------------------------------------------------------------------------------------------- depth preview
def test_the_depth_preview_is_turbo_of_inverse_depth_normalised_over_the_range_in_rgb_order() -> None:
    depth = np.random.default_rng(0).uniform(0.5, 30.0, (40, 50)).astype(np.float32)
    near, far = 1.0 * 1.3, 20.0 * 1.3
    inverse = (1.0 / depth - 1.0 / far) / (1.0 / near - 1.0 / far)
    expected = cv2.applyColorMap(np.clip(inverse * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    preview = depth_preview(depth, near, far)
    assert preview.dtype == np.uint8 and preview.shape == (40, 50, 3)
    np.testing.assert_array_equal(preview, expected)
    ends = depth_preview(np.array([[near, far]], np.float32), near, far)[0]
    assert ends[0, 0] > ends[0, 2] and ends[1, 2] > ends[1, 0]  # near is red, far is blue


# ------------------------------------------------------------------------------------------- frame sampler
@pytest.mark.parametrize("capacity", [1, 6])
def test_the_sampler_keeps_at_most_capacity_evenly_spaced_frames_from_the_first_over_the_whole_stream(
        capacity: int) -> None:
    for length in range(1, 101):
        sampler = FrameSampler(capacity)
        for arrival in range(length):
            sampler.add(10 + 3 * arrival, np.full((2, 2, 3), arrival % 256, np.uint8), np.zeros((2, 2, 3), np.uint8))
            assert len(sampler.samples) <= capacity  # bounded at every step, not just at the end
        arrivals = [(index - 10) // 3 for index, _, _ in sampler.samples]
        assert arrivals[0] == 0, length
        assert np.all(np.diff(arrivals) == sampler.stride), (length, arrivals)
        assert arrivals[-1] > length - 1 - sampler.stride  # the spacing reaches the end of the stream
        assert len(arrivals) >= min(length, capacity // 2 + 1)
        assert all(rgb[0, 0, 0] == arrival % 256 for arrival, (_, rgb, _) in zip(arrivals, sampler.samples))


def test_the_sampler_keeps_copies_so_the_caller_may_reuse_its_buffers() -> None:
    sampler = FrameSampler()
    buffer = np.zeros((4, 4, 3), np.uint8)
    sampler.add(0, buffer, buffer)
    buffer[:] = 255
    assert sampler.samples[0][1].max() == 0 and sampler.samples[0][2].max() == 0


def test_a_sampler_that_would_keep_nothing_is_refused() -> None:
    with pytest.raises(ValueError, match="capacity 0"):
        FrameSampler(0)


# ------------------------------------------------------------------------------------------------- video
def decode(path: Path) -> tuple[list[np.ndarray], float, str]:
    """The frames (RGB), the frame rate and the codec's name."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
        return frames, float(stream.average_rate), stream.codec_context.name


def panels(frame: np.ndarray, upscale: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The two panels of a decoded frame at their input size (the centre pixel of each enlarged pixel)."""
    small = frame[upscale // 2 :: upscale, upscale // 2 :: upscale][:height, : 2 * width].astype(np.int64)
    return small[:, :width], small[:, width:]


@pytest.mark.parametrize("encoder", [None, "mpeg4"])
def test_the_video_has_one_frame_per_input_frame_with_the_frame_left_and_its_depth_right(
        tmp_path: Path, encoder: str | None) -> None:
    rgb, preview = gradient_rgb(), gradient_preview()
    with SideBySideVideo(tmp_path / "video.mp4", 24.0, SIZE, SIZE, encoder=encoder) as video:
        for _ in range(10):
            video.add(rgb, preview)
    frames, rate, codec = decode(tmp_path / "video.mp4")
    assert video.upscale * SIZE >= 256  # a 64 px video is enlarged to be watchable (and more than a few blocks)
    assert len(frames) == 10 and rate == 24
    assert all(frame.shape == (video.upscale * SIZE, 2 * video.upscale * SIZE, 3) for frame in frames)
    for frame in frames:
        left, right = panels(frame, video.upscale, SIZE, SIZE)
        assert np.abs(left - rgb).mean() < 12 and np.abs(right - preview).mean() < 12
        assert np.abs(left - preview).mean() > 30  # the two sides are told apart
    if encoder is None:
        assert video.encoder == "libx264" and codec == "h264"


@pytest.mark.parametrize("fps", [0.0, float("nan"), float("inf")])
def test_a_video_without_a_known_frame_rate_plays_at_the_default_rate(tmp_path: Path, fps: float) -> None:
    with SideBySideVideo(tmp_path / "video.mp4", fps, SIZE, SIZE) as video:
        video.add(gradient_rgb(), gradient_preview())
    frames, rate, _ = decode(tmp_path / "video.mp4")
    assert len(frames) == 1 and rate == DEFAULT_FPS
    with pytest.raises(ValueError, match="positive frame rate"):
        SideBySideVideo(tmp_path / "other.mp4", -5.0, SIZE, SIZE)


def test_odd_panel_sizes_are_padded_to_the_even_size_yuv420p_needs(tmp_path: Path) -> None:
    height, width = 301, 75
    with SideBySideVideo(tmp_path / "video.mp4", 30.0, height, width) as video:
        video.add(gradient_rgb(height, width), gradient_preview(height, width))
    frames, _, _ = decode(tmp_path / "video.mp4")
    assert video.upscale == 1 and frames[0].shape == (302, 150, 3)
    left, right = panels(frames[0], 1, height, width)
    assert np.abs(left - gradient_rgb(height, width)).mean() < 12
    assert np.abs(right - gradient_preview(height, width)).mean() < 12


def test_a_frame_of_the_wrong_size_is_refused_and_a_failed_video_leaves_no_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="video preview: expected 64 x 64 x 3 uint8"):
        with SideBySideVideo(tmp_path / "video.mp4", 30.0, SIZE, SIZE) as video:
            video.add(gradient_rgb(), gradient_rgb())
            video.add(gradient_rgb(), gradient_preview(32, 32))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------ splat
K_SPLAT = np.array([[50.0, 0.0, 31.0], [0.0, 50.0, 23.0], [0.0, 0.0, 1.0]])
CAMERA = pose(yaw(0.3), (1.0, -2.0, 0.5))  # a camera away from the world origin, turned


def in_world(points_cam: np.ndarray) -> np.ndarray:
    return points_cam @ CAMERA[:3, :3].T + CAMERA[:3, 3]


def test_a_point_in_front_of_the_camera_lands_on_its_projected_pixel() -> None:
    point = in_world(np.array([[0.8, -0.4, 4.0]]))  # u = 50 * 0.2 + 31 = 41, v = 50 * -0.1 + 23 = 18
    image = splat_points(point, np.array([[200, 10, 20]], np.uint8), K_SPLAT, CAMERA, 48, 64)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8
    assert tuple(image[18, 41]) == (200, 10, 20)
    others = np.ones((48, 64), bool)
    others[18, 41] = False
    assert np.all(image[others] == BACKGROUND)


@pytest.mark.parametrize("order", [[0, 1], [1, 0]])
def test_of_two_points_on_one_pixel_the_nearer_wins_whatever_their_order(order: list[int]) -> None:
    near, far = np.array([0.2, 0.2, 2.0]), np.array([0.2, 0.2, 2.0]) * 3  # one ray: pixel (36, 28)
    vertices = in_world(np.stack([near, far]))[order]
    colours = np.array([[255, 0, 0], [0, 0, 255]], np.uint8)[order]
    image = splat_points(vertices, colours, K_SPLAT, CAMERA, 48, 64)
    assert tuple(image[28, 36]) == (255, 0, 0)
    assert np.count_nonzero(np.any(image != BACKGROUND, axis=-1)) == 1


def test_points_behind_the_camera_or_outside_the_image_are_dropped() -> None:
    behind = in_world(np.array([[0.0, 0.0, -3.0], [0.1, 0.1, 0.0]]))  # behind and in the camera's plane
    outside = in_world(np.array([[10.0, 0.0, 1.0], [0.0, -10.0, 1.0]]))
    image = splat_points(np.concatenate([behind, outside]), np.full((4, 3), 255, np.uint8), K_SPLAT, CAMERA, 48,
                         64, background=(1, 2, 3))
    assert np.all(image == (1, 2, 3))


def test_a_larger_splat_fills_the_square_around_the_projection_and_the_nearest_still_wins() -> None:
    vertices = in_world(np.array([[0.0, 0.0, 5.0], [0.04, 0.0, 2.0]]))  # pixels (31, 23) and (32, 23)
    image = splat_points(vertices, np.array([[0, 255, 0], [255, 0, 0]], np.uint8), K_SPLAT, CAMERA, 48, 64,
                         point_px=3)
    assert np.all(image[22:25, 30] == (0, 255, 0))  # only the far point reaches this column
    assert np.all(image[22:25, 31:34] == (255, 0, 0))  # the near point covers its 3 x 3 square
    assert np.count_nonzero(np.any(image != BACKGROUND, axis=-1)) == 12


def test_the_splat_grows_to_close_the_gaps_between_sparse_points_within_its_budget() -> None:
    K = np.array([[100.0, 0.0, 64.0], [0.0, 100.0, 64.0], [0.0, 0.0, 1.0]])
    grid = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 21), np.linspace(-0.4, 0.4, 21)), -1).reshape(-1, 2)
    plane = np.concatenate([grid, np.full((len(grid), 1), 1.0)], axis=1)  # points 4 px apart, face-on
    pixels, _ = nearest_points(plane, K, np.eye(4), 128, 128)
    point_px = splat_footprint(pixels, 128, len(plane))
    covered = np.zeros(128 * 128, bool)
    covered[nearest_points(plane, K, np.eye(4), 128, 128, point_px)[0]] = True
    assert covered.reshape(128, 128)[25:103, 25:103].all()  # no gap inside the plane
    grid = np.stack(np.meshgrid(np.arange(100), np.arange(100)), -1).reshape(-1, 2) / 100 - 0.5
    plane = np.concatenate([grid, np.full((len(grid), 1), 1.0)], axis=1)  # points 1 px apart
    dense, _ = nearest_points(plane, K, np.eye(4), 128, 128)
    assert splat_footprint(dense, 128, len(plane)) <= 2  # points on neighbouring pixels need little growing
    assert splat_footprint(pixels, 128, 10**6) == 1  # a million points cannot afford it


def test_the_overview_camera_is_behind_and_above_the_first_camera_and_frames_the_surface() -> None:
    vertices, _ = tube(5000)
    first = pose(yaw(0.4), (3.0, 1.0, -2.0))
    world = vertices @ first[:3, :3].T + first[:3, 3]
    K, T_world_view = overview_camera(world, first, 200)
    eye_in_first = np.linalg.inv(first) @ T_world_view[:, 3]
    assert eye_in_first[2] < 0 and eye_in_first[1] < 0  # behind (-z) and above (-y, as y points down)
    assert T_world_view[:3, 1] @ first[:3, 1] > 0  # the first camera's down is down in the view
    cam = (world - T_world_view[:3, 3]) @ T_world_view[:3, :3]
    u, v = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < 200) & (v >= 0) & (v < 200)
    assert inside.mean() > 0.98
    assert abs((u.min() + u.max()) / 2 - 99.5) < 10 and abs((v.min() + v.max()) / 2 - 99.5) < 10


# --------------------------------------------------------------------------------------------- the sheet
def test_the_top_view_shows_x_right_and_z_up_and_the_side_view_z_right_and_y_down() -> None:
    poses = np.stack([pose(translation=(1.0 * i, 2.0 * i, 3.0 * i)) for i in range(5)])
    figure = Figure()
    top, side = figure.add_subplot(1, 2, 1), figure.add_subplot(1, 2, 2)
    draw_path_top(top, poses)
    draw_path_side(side, poses)
    path_top = next(line for line in top.get_lines() if line.get_label() == "path")
    path_side = next(line for line in side.get_lines() if line.get_label() == "path")
    np.testing.assert_allclose(path_top.get_xdata(), poses[:, 0, 3])
    np.testing.assert_allclose(path_top.get_ydata(), poses[:, 2, 3])
    np.testing.assert_allclose(path_side.get_xdata(), poses[:, 2, 3])
    np.testing.assert_allclose(path_side.get_ydata(), poses[:, 1, 3])
    assert side.yaxis_inverted() and not top.yaxis_inverted()
    assert "cm" in top.get_xlabel() and "cm" in side.get_ylabel()
    assert top.get_aspect() == 1.0 and side.get_aspect() == 1.0


def sample(index: int) -> tuple[int, np.ndarray, np.ndarray]:
    return index, gradient_rgb(), gradient_preview()


def test_the_contact_sheet_is_a_wide_png_written_atomically(tmp_path: Path) -> None:
    vertices, colours = tube(20_000)
    write_contact_sheet(tmp_path / "sheet.png", [sample(i) for i in range(0, 60, 12)], PREVIEW_RANGE_CM,
                        path_along_z(60), vertices, colours, "S5: 60 frames, 64 px, 43 fps")
    image = cv2.imread(str(tmp_path / "sheet.png"))
    assert image is not None and image.shape[1] >= 1500 and image.shape[0] >= 800
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.png"]


def test_a_sheet_of_one_frame_and_no_surface_is_drawn_too(tmp_path: Path) -> None:
    write_contact_sheet(tmp_path / "sheet.png", [sample(0)], PREVIEW_RANGE_CM, path_along_z(1), np.zeros((0, 3)),
                        np.zeros((0, 3), np.uint8), "one frame")
    image = cv2.imread(str(tmp_path / "sheet.png"))
    assert image is not None and image.shape[1] >= 1500


def test_a_sheet_without_frames_or_with_colours_that_do_not_match_the_vertices_is_refused(tmp_path: Path) -> None:
    vertices, colours = tube(100)
    with pytest.raises(ValueError, match="at least one sampled frame"):
        write_contact_sheet(tmp_path / "sheet.png", [], PREVIEW_RANGE_CM, path_along_z(3), vertices, colours, "t")
    with pytest.raises(ValueError, match="100 vertices but 99 colours"):
        write_contact_sheet(tmp_path / "sheet.png", [sample(0)], PREVIEW_RANGE_CM, path_along_z(3), vertices,
                            colours[1:], "t")
    with pytest.raises(ValueError, match=r"ground-truth path: expected shape \[N, 3\] with N=3"):
        write_contact_sheet(tmp_path / "sheet.png", [sample(0)], PREVIEW_RANGE_CM, path_along_z(3), vertices,
                            colours, "t", gt_positions=np.zeros((2, 3)))
    assert not (tmp_path / "sheet.png").exists()


def colour_bars(figure: Figure) -> dict[str, object]:
    """``{label: colour bar}`` of the figure's colour bars (an inset colour bar is a child of its panel)."""
    every = [*figure.axes, *(child for axes in figure.axes for child in axes.child_axes)]
    return {axes._colorbar.ax.get_xlabel(): axes._colorbar for axes in every if hasattr(axes, "_colorbar")}


def test_every_depth_picture_of_the_sheet_has_a_colour_bar_in_cm_with_the_previews_colours() -> None:
    vertices, colours = tube(2_000)
    sheet = contact_sheet([sample(0), sample(12)], PREVIEW_RANGE_CM, path_along_z(20), vertices, colours, "t")
    bars = colour_bars(sheet)
    assert set(bars) == {"depth (cm)", "depth from the view (cm)"}
    near, far = PREVIEW_RANGE_CM
    depths = np.array([1.0, 1.3, 2.0, 3.5, 7.0, 19.0])
    expected = depth_preview(depths[None].astype(np.float32), near, far)[0] / 255.0
    # the bar's table and depth_preview's quantise inverse depth alike up to one entry of TURBO's 256
    np.testing.assert_allclose(bars["depth (cm)"].mappable.to_rgba(depths)[:, :3], expected, atol=0.04)
    ticks = bars["depth (cm)"].get_ticks()
    assert ticks.min() == pytest.approx(near) and ticks.max() == pytest.approx(far)


def surface_views(sheet: Figure) -> list:
    """The pixels of the sheet's two views of the surface, in colour and by depth."""
    views = [axes for axes in sheet.axes if axes.get_title().startswith(("fused surface", "by depth"))]
    return [axes.get_images()[0].get_array() for axes in views]


def test_a_surface_of_more_vertices_than_the_splat_takes_is_drawn_from_every_kth_and_titled_with_all(
        monkeypatch: pytest.MonkeyPatch) -> None:
    vertices, colours = tube(2_000)
    poses = path_along_z(20)
    alone = contact_sheet([sample(0)], PREVIEW_RANGE_CM, poses, vertices, colours, "t")
    monkeypatch.setattr(pictures, "SPLAT_POINTS", 2_000)
    # each vertex three times over, the second and third in red: every third vertex is the tube once, while all of
    # them would show red (of points at one depth the last listed wins)
    tripled, red = np.repeat(vertices, 3, axis=0), np.repeat(colours, 3, axis=0)
    red[1::3] = red[2::3] = (255, 0, 0)
    threefold = contact_sheet([sample(0)], PREVIEW_RANGE_CM, poses, tripled, red, "t")
    for drawn, expected in zip(surface_views(threefold), surface_views(alone), strict=True):
        np.testing.assert_array_equal(drawn, expected)
    assert "fused surface (6,000 vertices)" in [axes.get_title() for axes in threefold.axes]


def test_the_sheet_draws_the_ground_truth_path_beside_the_models_where_given() -> None:
    vertices, colours = tube(2_000)
    poses = path_along_z(20)
    truth = poses[:, :3, 3] + np.array([0.5, 0.0, 0.0])
    sheet = contact_sheet([sample(0)], PREVIEW_RANGE_CM, poses, vertices, colours, "t", gt_positions=truth)
    top, side = (axes for axes in sheet.axes if axes.get_title().startswith("camera path"))
    for axes, (horizontal, vertical) in ((top, (0, 2)), (side, (2, 1))):
        (drawn,) = [line for line in axes.get_lines() if line.get_label() == GROUND_TRUTH_LABEL]
        np.testing.assert_allclose(drawn.get_xdata(), truth[:, horizontal])
        np.testing.assert_allclose(drawn.get_ydata(), truth[:, vertical])
        assert GROUND_TRUTH_LABEL in [text.get_text() for text in axes.get_legend().get_texts()]
    without = contact_sheet([sample(0)], PREVIEW_RANGE_CM, poses, vertices, colours, "t")
    assert not [line for axes in without.axes for line in axes.get_lines()
                if line.get_label() == GROUND_TRUTH_LABEL]
