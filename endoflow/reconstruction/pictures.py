"""Pictures of a reconstruction a person looks at first: a PNG contact sheet and an MP4 of frame | depth.

- :class:`FrameSampler` keeps a few evenly spaced frames of a stream of unknown length in bounded memory, for the
  sheet's top rows.
- :class:`SideBySideVideo` streams ``rgb | depth preview`` into an MP4 (PyAV; H.264 ``libx264`` in yuv420p where
  the build has it, else MPEG-4 part 2), one video frame per input frame, never holding more than one. Panels
  smaller than :data:`MIN_VIDEO_HEIGHT` are enlarged by an integer factor with nearest neighbour (sharp pixels,
  and encoders work on blocks of 16 px: a 64 px video would be four blocks tall).
- :func:`write_contact_sheet` renders one PNG: the sampled frames above their depth previews and its colour bar,
  the camera path from the top and from the side (beside the ground-truth path where there is one), and the fused
  surface as a z-buffered point splat (:func:`splat_points`) from a virtual camera behind and above the first
  one, in its colours and by depth (with a colour bar).
- :func:`depth_preview` is the colour map of every depth preview: TURBO of inverse depth over a range;
  :func:`depth_colour_bar` draws its scale in cm.

Conventions (``docs/architecture.md``): OpenCV camera (x right, y down, z forward), poses ``T_world_cam``
camera-to-world, lengths in cm; images are ``H x W x 3`` uint8 in RGB order; pixel centres at integer
coordinates. The world frame of the sheet's views is the one the poses are in (the first camera's, in
``endoflow reconstruct``). Files are written atomically through :mod:`endoflow.io`.
"""

from __future__ import annotations

import io
import math
import sys
from contextlib import ExitStack
from fractions import Fraction
from pathlib import Path
from types import TracebackType
from typing import Optional

import av
import cv2
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import FuncNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.gridspec import GridSpecBase

from endoflow.data.video_encoding import video_encoder
from endoflow.io import atomic_path, write_bytes
from endoflow.shapes import check_shape

Sample = tuple[int, np.ndarray, np.ndarray]  # (frame index, rgb, depth preview)

DEFAULT_FPS = 30.0  # a video whose rate is unknown (0, NaN) plays at this rate
MIN_VIDEO_HEIGHT = 256  # px: smaller panels are enlarged by an integer factor up to at least this height
X264_CRF = "18"  # visually lossless; the default (23) smears the colour-mapped depth's bands
# x264's preset: at CRF 18 "veryfast" wrote files the size of the default's ("medium") in 40% of its CPU time (480 px
# panels: 12.0 against 29.5 ms a frame; 64 px: 3.9 against 8.5), time the write-behind thread would take from the
# networks on two cores, at 0.2-0.5 dB less PSNR against the frames (39-42 dB, image and depth panels, 40 frames)
X264_PRESET = "veryfast"
MPEG4_BITS_PER_PIXEL = 0.3  # per pixel per frame: MPEG-4's default 200 kbit/s blurs anything but a thumbnail

SHEET_WIDTH_IN = 16.0  # at SHEET_DPI: 1600 px wide
SHEET_DPI = 100
SHEET_MIN_COLUMNS = 6  # sample slots per row, so one sample is as big as one of six
SPLAT_SIZE = 320  # px of the surface views, about as large as they show on the sheet
FOOTPRINT_BLOCK = 8  # px: splats grow up to this size to close the gaps between sparse points
SPLAT_BUDGET = 2_000_000  # point squares per splat: 200k vertices at 3 x 3 px take about 0.2 s
# Vertices splatted at most (every k-th beyond): a 320 px view has 100k pixels, and a long video's surface has
# millions of vertices (15 million took the sheet 13 s on the H100 machine), which add time and memory but nothing
# the view can show.
SPLAT_POINTS = 1_000_000
BACKGROUND = (24, 24, 24)  # dark, so the tissue's colours stand out
DIRECTION_MARKS = 12  # viewing-direction segments drawn along the path
EMPTY_SURFACE_TEXT = "no surface (fusion off or nothing observed)"
COLOUR_BAR_TICKS = 5  # depth ticks of a colour bar, evenly spaced in inverse depth as its colours are
GROUND_TRUTH_LABEL = "ground truth (Sim(3)-aligned)"


def depth_preview(depth_cm: np.ndarray, min_depth_cm: float, max_depth_cm: float) -> np.ndarray:
    """RGB uint8 TURBO colour map of inverse depth normalised over ``[min_depth_cm, max_depth_cm]``: near is red,
    far is blue; depth outside the range is clipped to its ends, unknown depth (0) shows as nearest."""
    with np.errstate(divide="ignore"):
        inverse = (1.0 / depth_cm - 1.0 / max_depth_cm) / (1.0 / min_depth_cm - 1.0 / max_depth_cm)
    colours = cv2.applyColorMap(np.clip(inverse * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return colours[..., ::-1].copy()


def depth_colour_bar(figure: Figure, near_cm: float, far_cm: float, label: str, **placement) -> None:
    """A colour bar of :func:`depth_preview`'s colours over ``[near_cm, far_cm]``: the TURBO table against inverse
    depth (near at 0, far at 1 along the bar), ticks in cm evenly spaced in inverse depth; ``placement`` goes to
    :meth:`Figure.colorbar` (``cax`` or ``ax``, orientation)."""
    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1] / 255.0
    # the norm puts depth d at 1 - x along the bar, x = (1/d - 1/far) / (1/near - 1/far) being d's place in
    # depth_preview's table: the bar's table runs the other way, so d gets depth_preview's colour
    norm = FuncNorm((minus_inverse, minus_inverse), vmin=near_cm, vmax=far_cm)
    bar = figure.colorbar(ScalarMappable(norm, ListedColormap(table[::-1])), label=label, **placement)
    ticks = 1.0 / np.linspace(1.0 / near_cm, 1.0 / far_cm, COLOUR_BAR_TICKS)
    bar.set_ticks(ticks, labels=[f"{tick:.2g}" if tick < 10 else f"{tick:.0f}" for tick in ticks])


def minus_inverse(values: np.ndarray) -> np.ndarray:
    """``-1 / values``, increasing with depth, and its own inverse (matplotlib's axes also ask it about 0)."""
    with np.errstate(divide="ignore"):
        return -1.0 / np.asarray(values, dtype=np.float64)


class FrameSampler:
    """At most ``capacity`` evenly spaced samples of a stream of unknown length, in bounded memory.

    The item arriving ``n``-th (from 0) is kept while ``n`` is a multiple of ``stride``; when more than
    ``capacity`` are kept the stride doubles and the items off it are dropped. So the kept items are always
    arrivals ``0, stride, 2 stride, ...``: the first item is always among them, and past ``capacity`` items at
    least ``capacity // 2 + 1`` stay, spread over the whole stream. Kept images are copies: the caller may reuse
    its buffers.
    """

    def __init__(self, capacity: int = 6) -> None:
        if capacity < 1:
            raise ValueError(f"a frame sampler keeps at least one frame, got capacity {capacity}")
        self.capacity = capacity
        self.stride = 1
        self._arrived = 0
        self._kept: list[tuple[int, Sample]] = []  # (arrival number, sample)

    def add(self, index: int, rgb: np.ndarray, preview: np.ndarray) -> None:
        """Offer the next frame of the stream: ``index`` its frame index, ``rgb`` and ``preview`` HxWx3 uint8."""
        arrival = self._arrived
        self._arrived += 1
        if arrival % self.stride:
            return
        self._kept.append((arrival, (index, np.array(rgb), np.array(preview))))
        while len(self._kept) > self.capacity:
            self.stride *= 2
            self._kept = [(n, sample) for n, sample in self._kept if n % self.stride == 0]

    @property
    def samples(self) -> list[Sample]:
        """The kept ``(index, rgb, preview)`` in arrival order."""
        return [sample for _, sample in self._kept]


class SideBySideVideo:
    """An MP4 of ``rgb | preview`` side by side, one video frame per :meth:`add`, written as frames come.

    ``height`` and ``width`` are one panel's size (the video is two panels wide). Panels are enlarged by
    :attr:`upscale` (an integer, nearest neighbour) to at least :data:`MIN_VIDEO_HEIGHT` px tall, and the frame is
    padded by a black row/column to even dimensions (yuv420p halves the colour resolution). ``fps`` that is zero
    or not finite (an input without a known rate) becomes :data:`DEFAULT_FPS`; a negative one is an error.
    ``encoder`` names a PyAV encoder to use instead of :func:`endoflow.data.video_encoding.video_encoder`'s pick.

    Use as a context manager: the file appears at ``path`` (atomically) when the block ends without an error, and
    not at all otherwise.
    """

    def __init__(self, path: Path, fps: float, height: int, width: int, encoder: Optional[str] = None) -> None:
        if height < 1 or width < 1:
            raise ValueError(f"video panels need a positive size, got {height} x {width}")
        if fps < 0:
            raise ValueError(f"a video needs a positive frame rate, got {fps}")
        self.path = Path(path)
        self.fps = float(fps) if math.isfinite(fps) and fps > 0 else DEFAULT_FPS
        self._rate = Fraction(self.fps).limit_denominator(1001)  # 29.97 is 30000/1001
        self.panel_size = (height, width)
        self.upscale = max(1, math.ceil(MIN_VIDEO_HEIGHT / height))
        self.frame_size = (even(height * self.upscale), even(2 * width * self.upscale))
        self.encoder = encoder or video_encoder()
        self.frames = 0
        self._exits = ExitStack()

    def __enter__(self) -> SideBySideVideo:
        with ExitStack() as opening:  # an encoder that fails to open leaves no temporary behind
            temporary = opening.enter_context(atomic_path(self.path))
            self._container = opening.enter_context(av.open(str(temporary), mode="w", format="mp4"))
            self._stream = self._container.add_stream(self.encoder, rate=self._rate)
            self._stream.height, self._stream.width = self.frame_size
            self._stream.pix_fmt = "yuv420p"
            if self.encoder == "libx264":
                self._stream.options = {"crf": X264_CRF, "preset": X264_PRESET}
            elif self.encoder == "mpeg4":
                self._stream.bit_rate = int(MPEG4_BITS_PER_PIXEL * np.prod(self.frame_size) * self.fps)
            self._exits = opening.pop_all()
        return self

    def add(self, rgb: np.ndarray, preview: np.ndarray) -> None:
        """Encode one frame: ``rgb`` and ``preview`` ``H x W x 3`` uint8 (RGB), the panel size given."""
        for name, image in (("rgb", rgb), ("preview", preview)):
            if image.shape != (*self.panel_size, 3) or image.dtype != np.uint8:
                raise ValueError(f"video {name}: expected {self.panel_size[0]} x {self.panel_size[1]} x 3 uint8, "
                                 f"got {image.shape} {image.dtype}")
        frame = av.VideoFrame.from_ndarray(self._side_by_side(rgb, preview), format="rgb24")
        frame.pts = self.frames
        frame.time_base = 1 / self._rate
        self._container.mux(self._stream.encode(frame))
        self.frames += 1

    def _side_by_side(self, rgb: np.ndarray, preview: np.ndarray) -> np.ndarray:
        pair = np.concatenate([rgb, preview], axis=1)
        big = np.repeat(np.repeat(pair, self.upscale, axis=0), self.upscale, axis=1)
        height, width = self.frame_size
        return np.pad(big, ((0, height - big.shape[0]), (0, width - big.shape[1]), (0, 0)))

    def __exit__(self, kind: Optional[type[BaseException]], error: Optional[BaseException],
                 trace: Optional[TracebackType]) -> None:
        # the exits close the container, then rename the file into place, or remove it if given an error
        if error is None:
            try:
                self._container.mux(self._stream.encode(None))  # the frames the encoder still holds back
            except BaseException:
                self._exits.__exit__(*sys.exc_info())
                raise
        self._exits.__exit__(kind, error, trace)


def even(n: int) -> int:
    return n + n % 2


def splat_points(vertices: np.ndarray, colours: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, height: int,
                 width: int, background: tuple[int, int, int] = BACKGROUND, point_px: int = 1) -> np.ndarray:
    """``height x width x 3`` uint8 image of points ``vertices`` (``V x 3`` world) coloured ``colours`` (``V x 3``
    uint8) seen by a pinhole camera ``K`` at ``T_world_cam``, as :func:`nearest_points` places them; pixels
    without a point are ``background``."""
    return paint(nearest_points(vertices, K, T_world_cam, height, width, point_px), colours, height, width,
                 background)


def nearest_points(vertices: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, height: int, width: int,
                   point_px: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A z-buffer: ``(pixels, winners)``, the flat indices (``v * width + u``) of the pixels points reach and the
    index of the vertex each shows. Each point fills the ``point_px`` x ``point_px`` square around the pixel
    nearest its projection (an even size extends right and down); the nearest point (smallest z) wins a pixel
    (of points at equal depth, the one listed last); points behind the camera (z <= 0) or outside the image are
    dropped. ``pixels`` are in increasing order."""
    T_cam_world = np.linalg.inv(T_world_cam)
    cam = vertices @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    ahead = cam[:, 2] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2])
        v = np.rint(K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2])
    # only points whose square reaches the image go on: the rest could overflow the integer pixel coordinates
    vertex = np.flatnonzero(ahead & (u > -point_px) & (u < width + point_px) & (v > -point_px)
                            & (v < height + point_px))
    offsets = np.arange(point_px) - (point_px - 1) // 2
    columns = u[vertex].astype(np.int64)[:, None] + offsets  # [points, point_px]
    rows = v[vertex].astype(np.int64)[:, None] + offsets
    inside = (((rows >= 0) & (rows < height))[:, :, None]) & (((columns >= 0) & (columns < width))[:, None, :])
    point, row, column = np.nonzero(inside)  # each pixel of each point's square inside the image
    pixel = rows[point, row] * width + columns[point, column]
    z, vertex = cam[vertex[point], 2], vertex[point]
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, pixel, z)  # unbuffered: every point of a pixel counts, in linear time (no sort)
    nearest = z == depth[pixel]
    winner = np.full(height * width, -1)
    np.maximum.at(winner, pixel[nearest], vertex[nearest])  # points at equal depth: the last vertex, every time
    pixels = np.flatnonzero(winner >= 0)
    return pixels, winner[pixels]


def paint(visible: tuple[np.ndarray, np.ndarray], colours: np.ndarray, height: int, width: int,
          background: tuple[int, int, int] = BACKGROUND) -> np.ndarray:
    """The image of :func:`nearest_points`' ``(pixels, winners)`` with the winners' ``colours``."""
    pixels, winners = visible
    image = np.empty((height, width, 3), np.uint8)
    image[:] = background
    image.reshape(-1, 3)[pixels] = colours[winners]
    return image


def overview_camera(vertices: np.ndarray, first_pose: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(K, T_world_cam)`` of a square ``size`` px virtual camera behind and above the first camera, looking at
    the vertices' centroid, its image framing nearly all of them (outliers may fall outside) in the middle.

    "Above" is against the first camera's y (down) axis, and the virtual camera keeps that axis pointing down on
    the image, so the view is upright as the video is."""
    centroid = vertices.mean(axis=0)
    radius = max(float(np.percentile(np.linalg.norm(vertices - centroid, axis=1), 95)), 1e-3)
    rotation, origin = first_pose[:3, :3], first_pose[:3, 3]
    eye = origin + rotation @ np.array([0.0, -0.8 * radius, -1.2 * radius])
    forward = centroid - eye
    if np.linalg.norm(forward) < 1e-9:  # the centroid at the eye: look along the first camera's axis
        forward = rotation[:, 2]
    forward = forward / np.linalg.norm(forward)
    down = rotation[:, 1]
    right = np.cross(down, forward)
    if np.linalg.norm(right) < 1e-6:  # looking straight up or down: keep the first camera's x as right
        right = rotation[:, 0]
    right = right / np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    pose[:3, 3] = eye
    cam = (vertices - eye) @ pose[:3, :3]
    ahead = cam[:, 2] > 1e-6
    tangents = cam[ahead, :2] / cam[ahead, 2:] if ahead.any() else np.zeros((1, 2))
    low, high = np.percentile(tangents, [0.5, 99.5], axis=0)
    middle = (low + high) / 2
    focal = size / (max(float((high - low).max()), 1e-6) * 1.1)  # the surface's extent, with a margin
    centre = (size - 1) / 2 - focal * middle  # the principal point that puts the surface in the middle
    K = np.array([[focal, 0.0, centre[0]], [0.0, focal, centre[1]], [0.0, 0.0, 1.0]])
    return K, pose


def splat_footprint(pixels: np.ndarray, size: int, points: int) -> int:
    """The splat size (px) that closes the gaps between ``points`` points whose single pixels landed on
    ``pixels`` (flat indices) of a ``size`` x ``size`` image. Their spacing is about sqrt(area / pixels reached),
    the area being that of the :data:`FOOTPRINT_BLOCK`-pixel blocks with a point in them (which the points fill
    if they are at most a block apart). The splat costs ``points`` x its size squared: that stays within
    :data:`SPLAT_BUDGET`."""
    blocks = np.unique((pixels // size) // FOOTPRINT_BLOCK * size + (pixels % size) // FOOTPRINT_BLOCK)
    spacing = math.sqrt(len(blocks) * FOOTPRINT_BLOCK**2 / max(len(pixels), 1))
    affordable = math.isqrt(max(SPLAT_BUDGET // max(points, 1), 1))
    return int(np.clip(math.ceil(1.5 * spacing), 1, min(FOOTPRINT_BLOCK, affordable)))  # 1.5: points lie unevenly


def write_contact_sheet(path: Path, samples: list[Sample], depth_range_cm: tuple[float, float], poses: np.ndarray,
                        vertices: np.ndarray, colours: np.ndarray, title: str,
                        gt_positions: Optional[np.ndarray] = None) -> None:
    """:func:`contact_sheet` as one PNG at ``path`` (about 1600 px wide), written atomically."""
    figure = contact_sheet(samples, depth_range_cm, poses, vertices, colours, title, gt_positions)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=SHEET_DPI)
    write_bytes(path, buffer.getvalue())


def contact_sheet(samples: list[Sample], depth_range_cm: tuple[float, float], poses: np.ndarray,
                  vertices: np.ndarray, colours: np.ndarray, title: str,
                  gt_positions: Optional[np.ndarray] = None) -> Figure:
    """``samples`` (``(index, rgb, preview)``, at least one) as frames above their depth previews (coloured over
    ``depth_range_cm`` by :func:`depth_preview`, with a colour bar), the camera path ``poses`` (``N x 4 x 4``
    camera-to-world, cm, N >= 1) from the top and the side, with ``gt_positions`` (``N x 3``, the ground truth in
    the path's world, aligned as the measurement aligns it) where given, and the surface ``vertices`` (``V x 3``
    cm, V may be 0) with ``colours`` (``V x 3`` uint8) splatted from a virtual camera behind and above the first
    camera, in colour and by depth; ``title`` on top."""
    if not samples:
        raise ValueError("a contact sheet needs at least one sampled frame")
    poses = np.asarray(poses, dtype=np.float64)
    check_shape("camera path", poses, "N,4,4")
    if len(poses) == 0:
        raise ValueError("camera path: expected at least one pose")
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
    if len(vertices) != len(colours):
        raise ValueError(f"surface: {len(vertices)} vertices but {len(colours)} colours")
    if gt_positions is not None:
        check_shape("ground-truth path", np.asarray(gt_positions), "N,3", N=len(poses))
    columns = max(len(samples), SHEET_MIN_COLUMNS)
    samples_height = SHEET_WIDTH_IN / columns * 2 + 0.6  # two rows of squares and the colour bar under them
    figure = Figure(figsize=(SHEET_WIDTH_IN, samples_height + 5.6), dpi=SHEET_DPI)
    FigureCanvasAgg(figure)
    figure.subplots_adjust(left=0.055, right=0.98, top=0.92, bottom=0.07)  # room for a title of two lines and long ticks
    rows = figure.add_gridspec(2, 1, height_ratios=[samples_height, 4.6], hspace=0.16)
    grid = rows[0].subgridspec(3, 2 * columns, hspace=0.15, wspace=0.1,
                               height_ratios=[SHEET_WIDTH_IN / columns] * 2 + [0.12])
    draw_samples(figure, grid, samples, columns)
    sampled = slice(columns - len(samples), columns + len(samples))  # the colour bar spans the samples
    depth_colour_bar(figure, *depth_range_cm, "depth (cm)", cax=figure.add_subplot(grid[2, sampled]),
                     orientation="horizontal")
    views = rows[1].subgridspec(1, 4, wspace=0.3)
    draw_path_top(figure.add_subplot(views[0]), poses, gt_positions)
    draw_path_side(figure.add_subplot(views[1]), poses, gt_positions)
    draw_surface(figure.add_subplot(views[2]), figure.add_subplot(views[3]), vertices, colours, poses[0])
    figure.suptitle(title, fontsize=14, wrap=True, y=0.995)  # a long input path wraps rather than running off the sheet
    return figure


def draw_samples(figure: Figure, grid: GridSpecBase, samples: list[Sample], columns: int) -> None:
    """Each sample in a column, its frame above its depth; fewer samples than columns sit in the middle (the grid
    has two cells per column, so an odd gap splits evenly)."""
    first = columns - len(samples)
    for column, (index, rgb, preview) in enumerate(samples):
        cells = slice(first + 2 * column, first + 2 * column + 2)
        frame_axis, depth_axis = figure.add_subplot(grid[0, cells]), figure.add_subplot(grid[1, cells])
        frame_axis.imshow(rgb, interpolation="nearest")
        frame_axis.set_title(f"frame {index}", fontsize=10)
        depth_axis.imshow(preview, interpolation="nearest")
        depth_axis.set_title("depth", fontsize=9)
        for axis in (frame_axis, depth_axis):
            axis.axis("off")


def draw_path_top(axis: Axes, poses: np.ndarray, gt_positions: Optional[np.ndarray] = None) -> None:
    """The path seen looking down (+y) onto the x-z plane: x to the right, z (forward) up."""
    draw_path(axis, poses, horizontal=0, vertical=2, gt_positions=gt_positions)
    axis.set(title="camera path from the top", xlabel="x (cm)", ylabel="z (cm)")


def draw_path_side(axis: Axes, poses: np.ndarray, gt_positions: Optional[np.ndarray] = None) -> None:
    """The path seen from the side on the z-y plane: z (forward) to the right, y (down) pointing down."""
    draw_path(axis, poses, horizontal=2, vertical=1, gt_positions=gt_positions)
    axis.invert_yaxis()
    axis.set(title="camera path from the side", xlabel="z (cm)", ylabel="y (cm, down)")


def draw_path(axis: Axes, poses: np.ndarray, horizontal: int, vertical: int,
              gt_positions: Optional[np.ndarray] = None) -> None:
    """Positions on two world axes, short segments of the camera's +z every few frames, start and end marked; the
    ground-truth path under it where given, so a path that went wrong shows."""
    positions = poses[:, :3, 3]
    extent = float(np.ptp(positions, axis=0).max())
    length = 0.08 * extent if extent > 1e-6 else 1.0  # a still camera still shows where it looks
    marked = np.arange(0, len(poses), max(1, len(poses) // DIRECTION_MARKS))
    tips = positions[marked] + length * poses[marked, :3, 2]
    segments = np.stack([positions[marked], tips], axis=1)[:, :, [horizontal, vertical]]
    axis.add_collection(LineCollection(segments, colors="tab:orange", linewidths=1.0, label="viewing direction"))
    if gt_positions is not None:
        axis.plot(gt_positions[:, horizontal], gt_positions[:, vertical], color="black", linestyle="--",
                  linewidth=1.2, label=GROUND_TRUTH_LABEL)
    axis.plot(positions[:, horizontal], positions[:, vertical], color="tab:blue", linewidth=1.2, label="path")
    axis.scatter(positions[:1, horizontal], positions[:1, vertical], color="tab:green", s=30, zorder=3,
                 label="start")
    if len(poses) > 1:
        axis.scatter(positions[-1:, horizontal], positions[-1:, vertical], color="tab:red", marker="x", s=30,
                     zorder=3, label="end")
    axis.set_aspect("equal", adjustable="datalim")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7, loc="best", framealpha=0.6)  # the path shows through where it must pass under


def draw_surface(colour_axis: Axes, depth_axis: Axes, vertices: np.ndarray, colours: np.ndarray,
                 first_pose: np.ndarray) -> None:
    """The surface splatted from the overview camera in its own colours and coloured by depth from it (at most
    :data:`SPLAT_POINTS` of its vertices, evenly through the list)."""
    for axis in (colour_axis, depth_axis):
        axis.axis("off")
    if len(vertices) == 0:
        colour_axis.text(0.5, 0.5, EMPTY_SURFACE_TEXT, ha="center", va="center", wrap=True, fontsize=11,
                         transform=colour_axis.transAxes)
        colour_axis.set_title("fused surface")
        return
    colour_axis.set_title(f"fused surface ({len(vertices):,} vertices)")
    every = math.ceil(len(vertices) / SPLAT_POINTS)
    vertices, colours = vertices[::every], colours[::every]
    K, pose = overview_camera(vertices, first_pose, SPLAT_SIZE)
    point_px = splat_footprint(nearest_points(vertices, K, pose, SPLAT_SIZE, SPLAT_SIZE)[0], SPLAT_SIZE,
                               len(vertices))
    visible = nearest_points(vertices, K, pose, SPLAT_SIZE, SPLAT_SIZE, point_px)
    colour_axis.imshow(paint(visible, colours, SPLAT_SIZE, SPLAT_SIZE), interpolation="nearest")
    z = (vertices - pose[:3, 3]) @ pose[:3, 2]
    near, far = np.percentile(z, [1, 99])
    near = max(float(near), 1e-3)  # points behind the view are not drawn; inverse depth needs near > 0
    depth_colours = depth_preview(np.clip(z, near, far)[:, None], float(near), float(max(far, near * 1.001)))[:, 0]
    depth_axis.imshow(paint(visible, depth_colours, SPLAT_SIZE, SPLAT_SIZE), interpolation="nearest")
    depth_axis.set_title("by depth from the view")
    # under the view, not taken from it: both views of the surface stay the same size
    depth_colour_bar(depth_axis.figure, float(near), float(max(far, near * 1.001)), "depth from the view (cm)",
                     cax=depth_axis.inset_axes([0.0, -0.09, 1.0, 0.045]), orientation="horizontal")
