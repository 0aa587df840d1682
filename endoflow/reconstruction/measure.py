"""A reconstruction measured against exact ground truth: the camera path and the fused surface, beside the
fusion's own floor and the trivial baselines, so a figure shows where the model stands between trivial and
perfect.

What is compared (all in the ground truth's world frame, cm):

- **Path**: APE of positions (RMSE, mean, median) and RPE between consecutive frames (translation in cm,
  rotation in degrees), computed with ``evo`` after aligning the path onto the ground-truth path
  (:mod:`endoflow.reconstruction.alignment`: Umeyama on positions, as ``evo``'s ``align``): Sim(3) for the model
  (monocular: its scale is unknown), SE(3) for the constant-velocity baseline (metric: the training set's mean
  step).
- **Surface**: the ground-truth surface is the renderer's exact geometry where the sequence sees it, sampled by
  back-projecting each frame's exact depth along the exact poses and thinned to one point per half voxel. A
  reconstruction's mesh vertices are mapped by its path's alignment; *accuracy* is the distance from each vertex
  to the nearest ground-truth point, *completeness* from each ground-truth point to the nearest vertex (mean and
  median, cm), and ``completeness_ratio`` the share of ground-truth points within two voxels of the mesh.

Rows of the surface table, each fused with the reconstruction's TSDF (voxel, truncation) brought to the ground
truth's scale (times the median ratio of the ground truth's depth to the model's, which also sets the distance
``completeness_ratio`` counts within). The model's own mesh is mapped by its path's Sim(3) scale, so its voxel
there is the reconstruction's times the path's scale: the same as the rows' where path and depth share one scale
(``scale_over_depth`` 1), coarser where the path's scale is larger:

- ``ground_truth``: GT depth along the GT path, the fusion's floor;
- ``model``: the reconstruction's own mesh (model depth along the model path);
- ``model_depth_gt_path``: model depth (times the ground truth's median depth ratio) along the GT path, the
  depth's share of the error;
- ``constant_depth``: the training set's mean GT depth everywhere, along the GT path;
- ``constant_velocity``: GT depth along the training set's mean step, chained from the first frame;
- ``trivial``: constant depth along constant velocity.

Baselines with a metric scale are aligned by SE(3), the model by Sim(3): the usual monocular protocol.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from endoflow.config import Params
from endoflow.data.imageio import read_gray16
from endoflow.data.frame_encoding import resize_depth, resize_rgb
from endoflow.data.trajectory_files import read_tum
from endoflow.devices import use_cpu_threads
from endoflow.geometry.direct_alignment import tracker_settings
from endoflow.io import write_bytes, write_csv, write_json
from endoflow.models.mlflow_model import is_model_uri, local_model_file
from endoflow.models.model_file import TrainingBaselines, load_model_file
from endoflow.reconstruction.alignment import Alignment, align_trajectory, trajectories
from endoflow.reconstruction.frames import DatasetFrames, FrameRange, FrameSource, InputFrame
from endoflow.reconstruction.fusion import TSDFVolume, read_ply_vertices
from endoflow.reconstruction.reconstruct import (NETWORK_PATH_FILE, Adaptation, ReconstructOptions,
                                                 log_reconstruction, reconstruct)

SURFACE_ROWS = ("ground_truth", "model", "model_depth_gt_path", "constant_depth", "constant_velocity", "trivial")
PATH_ROWS = ("model", "network", "constant_velocity")  # network: the pose network's own chain, where refined
COMPLETE_WITHIN_VOXELS = 2.0  # completeness_ratio: ground-truth points this many voxels from the mesh at most
GT_POINT_SPACING_VOXELS = 0.5  # the ground-truth surface keeps one point per half voxel
# Distances are capped here: a vertex this far off is simply wrong, and the search stops there.
DISTANCE_CAP_CM = 5.0
# A point centimetres off a surface sampled every 0.01 cm (480 px) is nearly as far from thousands of its points,
# and the k-d tree visits all their leaves: large leaves make that 3x cheaper than scipy's default of 16, and
# cost nothing for near points (an untrained model's trivial rows at 480 px: 238 s with 16, 33 s with 256 and
# both cores; see docs/reconstruction.md).
KD_TREE_LEAF_SIZE = 256
# Each side of a distance is an evenly strided sample of at most this many points: at 480 px a surface has
# millions of vertices, and the statistics of 100k are the same to three digits.
MAX_MEASURED_POINTS = 100_000
MEASUREMENT_FILE = "measurement.json"  # every figure, beside the reconstruction it measures
PATH_ERRORS_FILE = "path_errors.csv"  # per-frame position errors of each path row, charted by `dvc plots`


def measure_reconstruction(source: FrameSource, out_dir: Path, baselines: TrainingBaselines) -> dict:
    """Path and surface errors of the reconstruction in ``out_dir`` (written by
    :func:`endoflow.reconstruction.reconstruct.reconstruct` from ``source``, which must carry ground-truth depth
    and poses), with the floor and the baselines of the module docstring; plain numbers plus ``per_frame``
    position errors of each path row."""
    summary = json.loads((out_dir / "reconstruction.json").read_text())
    if summary.get("tsdf") is None:
        raise ValueError(f"{out_dir}: the reconstruction was run without fusion; measuring needs its surface")
    frames = FrameRange(**summary["frame_range"])
    size, K = int(summary["size"]), np.asarray(summary["K"], np.float64)
    depth_scale = float(summary.get("ground_truth_scale", {}).get("median", 1.0))
    # the rows fuse depth at the ground truth's scale: the reconstruction's voxel and truncation are brought there,
    # so that a voxel spans as much of the scene in every row as in the model's own surface
    voxel, trunc = (float(summary["tsdf"][key]) * depth_scale for key in ("voxel_cm", "trunc_cm"))
    _, model_poses = read_tum(out_dir / "trajectory.tum")
    step = np.linalg.matrix_power(np.asarray(baselines.mean_relative_pose, np.float64), frames.stride)
    volumes = {row: TSDFVolume(voxel, trunc) for row in SURFACE_ROWS if row != "model"}
    surface = SurfacePoints(voxel * GT_POINT_SPACING_VOXELS)
    gt_poses, velocity_poses = [], [np.eye(4)]
    for n, (frame, model_depth) in enumerate(_frames_with_model_depth(source, frames, out_dir, summary)):
        gt_depth, gt_pose = _ground_truth(frame, size, source)
        rgb = resize_rgb(frame.rgb, size)
        if n:
            velocity_poses.append(velocity_poses[-1] @ step)
        constant = np.where(gt_depth > 0, np.float32(baselines.mean_depth_cm), np.float32(0))
        inputs = {"ground_truth": (gt_depth, gt_pose),
                  "model_depth_gt_path": (model_depth * depth_scale, gt_pose),
                  "constant_depth": (constant, gt_pose),
                  "constant_velocity": (gt_depth, velocity_poses[-1]),
                  "trivial": (constant, velocity_poses[-1])}
        for row, (depth, pose) in inputs.items():
            volumes[row].integrate(depth, rgb, K, pose)
        surface.add(gt_depth, K, gt_pose)
        gt_poses.append(gt_pose)
    gt_poses = np.stack(gt_poses)
    if len(gt_poses) != len(model_poses):
        raise ValueError(f"{out_dir}: trajectory.tum has {len(model_poses)} poses for {len(gt_poses)} frames of "
                         f"{source.description}")
    paths = {"model": (model_poses, True), "constant_velocity": (np.stack(velocity_poses), False)}
    # the pose network's own chain: beside a refined path, its own file; else the path itself
    network = out_dir / NETWORK_PATH_FILE
    paths["network"] = (read_tum(network)[1] if network.is_file() else model_poses, True)
    path_results = {row: path_errors(gt_poses, poses, with_scale) for row, (poses, with_scale) in paths.items()}
    for row in ("model", "network"):
        # the path's scale over the depth's: 1 where a length measured in the map is a length in the depth's unit
        path_results[row]["scale_over_depth"] = path_results[row]["scale"] / depth_scale
    alignments = {row: result.pop("alignment") for row, result in path_results.items()}
    alignments["trivial"] = alignments["constant_velocity"]
    identity = Alignment(np.eye(3), np.zeros(3), 1.0)
    meshes = {row: volume.extract_mesh().vertices for row, volume in volumes.items()}
    meshes["model"] = read_ply_vertices(out_dir / "mesh.ply")
    gt_points = surface.points()
    surface_results = {row: surface_errors(alignments.get(row, identity).apply(meshes[row]), gt_points, voxel)
                       for row in SURFACE_ROWS}
    return {"frames": len(gt_poses), "voxel_cm": voxel, "depth_scale": depth_scale,
            "frames_per_second": float(summary["frames_per_second"]),
            "path": path_results, "surface": surface_results}


def path_errors(gt_poses: np.ndarray, poses: np.ndarray, with_scale: bool) -> dict:
    """``evo`` APE (positions) and RPE (consecutive frames) of ``poses`` after aligning them onto ``gt_poses``
    (Sim(3) ``with_scale``, else SE(3)); ``alignment`` holds the transform, ``per_frame`` the position errors."""
    from evo.core import metrics

    reference, estimate = trajectories(gt_poses, poses)
    alignment = align_trajectory(estimate, reference, with_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    result = {"ate_rmse": float(ape.get_statistic(metrics.StatisticsType.rmse)),
              "ate_mean": float(ape.get_statistic(metrics.StatisticsType.mean)),
              "ate_median": float(ape.get_statistic(metrics.StatisticsType.median)),
              "scale": alignment.scale}
    if len(gt_poses) > 1:
        for key, relation in (("rpe_trans", metrics.PoseRelation.translation_part),
                              ("rpe_rot", metrics.PoseRelation.rotation_angle_deg)):
            rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
            rpe.process_data((reference, estimate))
            result[key] = float(rpe.get_statistic(metrics.StatisticsType.mean))
    return {**result, "alignment": alignment, "per_frame": np.asarray(ape.error, np.float64)}


def surface_errors(vertices: np.ndarray, gt_points: np.ndarray, voxel_cm: float) -> dict[str, float]:
    """Accuracy (vertices to the ground truth) and completeness (ground truth to the vertices), cm, each distance
    capped at :data:`DISTANCE_CAP_CM`; an empty mesh has no accuracy (None: JSON has no NaN) and every ground-truth
    point at the cap."""
    if len(gt_points) == 0:
        raise ValueError("the ground truth has no surface points: no frame has valid depth")
    if len(vertices) == 0:
        return {"accuracy_mean": None, "accuracy_median": None, "completeness_mean": DISTANCE_CAP_CM,
                "completeness_median": DISTANCE_CAP_CM, "completeness_ratio": 0.0}
    accuracy = capped_distances(gt_points, evenly_strided(vertices))
    completeness = capped_distances(vertices, evenly_strided(gt_points))
    return {"accuracy_mean": float(accuracy.mean()), "accuracy_median": float(np.median(accuracy)),
            "completeness_mean": float(completeness.mean()), "completeness_median": float(np.median(completeness)),
            "completeness_ratio": float(np.mean(completeness <= COMPLETE_WITHIN_VOXELS * voxel_cm))}


def evenly_strided(points: np.ndarray) -> np.ndarray:
    """At most :data:`MAX_MEASURED_POINTS` of ``points``, every k-th (deterministic, spread over the surface)."""
    return points[::max(1, int(np.ceil(len(points) / MAX_MEASURED_POINTS)))]


def capped_distances(targets: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact distance from each of ``points`` to the nearest of ``targets``, at most :data:`DISTANCE_CAP_CM` (the
    same for any number of cores: the search runs on all of them)."""
    tree = cKDTree(targets, leafsize=KD_TREE_LEAF_SIZE)
    distances, _ = tree.query(points, distance_upper_bound=DISTANCE_CAP_CM, workers=-1)
    return np.minimum(distances, DISTANCE_CAP_CM)


class SurfacePoints:
    """Ground-truth surface samples, one per cell of ``spacing_cm`` (the first seen): memory follows the surface
    seen, not the number of frames."""

    def __init__(self, spacing_cm: float) -> None:
        self.spacing = spacing_cm
        self._keys = np.zeros((0, 3), np.int64)
        self._points = np.zeros((0, 3))

    def add(self, depth_cm: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        points = np.concatenate([self._points, back_project(depth_cm, K, T_world_cam)])
        keys = np.concatenate([self._keys, np.floor(points[len(self._points):] / self.spacing).astype(np.int64)])
        _, first = np.unique(keys, axis=0, return_index=True)
        kept = np.sort(first)  # np.unique returns each key's first occurrence: earlier frames win
        self._keys, self._points = keys[kept], points[kept]

    def points(self) -> np.ndarray:
        return self._points


def back_project(depth_cm: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """World points (cm) of every pixel with depth > 0: pixel centres at integer coordinates, as K is stored."""
    rows, cols = np.nonzero(depth_cm > 0)
    z = depth_cm[rows, cols].astype(np.float64)
    camera = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return camera @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def _ground_truth(frame: InputFrame, size: int, source: FrameSource) -> tuple[np.ndarray, np.ndarray]:
    if frame.depth_cm is None or frame.T_world_cam is None:
        raise ValueError(f"{source.description}: frame {frame.index} has no ground-truth depth and pose to measure "
                         f"against")
    return resize_depth(np.asarray(frame.depth_cm, np.float32), size), np.asarray(frame.T_world_cam, np.float64)


def _frames_with_model_depth(source: FrameSource, frames: FrameRange, out_dir: Path,
                             summary: dict) -> Iterator[tuple[InputFrame, np.ndarray]]:
    unit = float(summary["depth_unit_cm"])
    for frame in source.frames(frames):
        counts = read_gray16(out_dir / "depth" / f"{frame.index:06d}.png")
        yield frame, counts.astype(np.float32) * np.float32(unit)


def per_frame_path_errors(result: dict) -> list[dict[str, float]]:
    """Rows ``frame, <path row>...`` of position errors after alignment, for a CSV plot."""
    columns = {row: result["path"][row]["per_frame"] for row in PATH_ROWS}
    count = len(next(iter(columns.values())))
    return [{"frame": i, **{row: float(values[i]) for row, values in columns.items()}} for i in range(count)]


def metrics_summary(result: dict) -> dict:
    """The metrics file's content: ``result`` without its per-frame arrays."""
    path = {row: {k: v for k, v in values.items() if k != "per_frame"} for row, values in result["path"].items()}
    return {**result, "path": path}


@contextlib.contextmanager
def stage_model_file(params: Params, project_root: str | Path = ".") -> Iterator[Path]:
    """The file of ``reconstruct.model``: a path in the project, or for a ``models:/`` URI the logged model's file,
    downloaded from the store of ``tracking.uri`` for the duration."""
    root = Path(project_root).resolve()
    location = params.reconstruct.model
    if not is_model_uri(location):
        yield root / location
        return
    from endoflow.tracking import tracking_uri  # MLflow takes seconds to import: only a URI pays for it
    with local_model_file(location, tracking_uri(params, root)) as path:
        yield path


def run_reconstruction(params: Params, name: str, model_path: Path, project_root: str | Path = ".",
                       adaptation: Optional[Adaptation] = None) -> dict:
    """The ``reconstruct`` stage for ``reconstruct.sequences.<name>``: reconstruct the sequence with the trained
    model at ``model_path`` (:func:`stage_model_file`; or, where ``adaptation`` was kept, the model fitted to the
    sequence first) into ``<reconstruct.out>/<name>/``, measure it (:func:`measure_reconstruction`) and log the
    figures and pictures into the model's MLflow run (:func:`log_measurement`). Every figure goes beside the
    reconstruction
    (:data:`MEASUREMENT_FILE`, and per-frame path errors in :data:`PATH_ERRORS_FILE`);
    ``<reconstruct.metrics>/<name>.json``, the file DVC reads, holds the headline (:func:`dvc_metrics`, shown by
    ``dvc exp show`` as ``reconstruct_simcol_S5.ate_cm``); ``<reconstruct.plots>/<name>/sheet.png`` is the picture
    sheet."""
    cfg = params.reconstruct
    item = cfg.sequences[name]
    root = Path(project_root).resolve()
    use_cpu_threads(params.threads)
    record = load_model_file(model_path)  # its baselines and run: a fitted model keeps both
    source = DatasetFrames(root / getattr(params.data, item.dataset).root, item.sequence, params)
    out_dir = root / cfg.out / name
    options = ReconstructOptions(FrameRange(item.start, item.stop, item.stride), cfg.size, 1.0, cfg.voxel_cm,
                                 cfg.trunc_cm, device=cfg.device, precision=cfg.precision,
                                 refine=tracker_settings(params.refine) if params.refine.enabled else None)
    reconstruct(source, source.K, model_path, out_dir, options, adaptation=adaptation)
    result = measure_reconstruction(source, out_dir, record.baselines)
    write_json(out_dir / MEASUREMENT_FILE, metrics_summary(result))
    write_json(root / cfg.metrics / f"{name}.json", dvc_metrics(name, result))
    write_csv(out_dir / PATH_ERRORS_FILE, pd.DataFrame(per_frame_path_errors(result)))
    write_bytes(root / cfg.plots / name / "sheet.png", (out_dir / "sheet.png").read_bytes())
    log_measurement(params, root, record.mlflow_run_id, name, out_dir, result)
    return result


def headline_measurement(result: dict) -> dict[str, Optional[float]]:
    """Three numbers per sequence for ``dvc exp show``, named with their units: the model's path ATE RMSE (cm),
    its surface's median accuracy (cm; None for a mesh without vertices) and the share of the ground-truth surface
    within :data:`COMPLETE_WITHIN_VOXELS` voxels of it (%). Constant velocity's figures are in
    :data:`MEASUREMENT_FILE`."""
    return {"ate_cm": result["path"]["model"]["ate_rmse"],
            "accuracy_cm": result["surface"]["model"]["accuracy_median"],
            f"completeness_{COMPLETE_WITHIN_VOXELS:g}vox_pct": 100.0 * result["surface"]["model"]["completeness_ratio"]}


def dvc_metrics(name: str, result: dict) -> dict[str, dict[str, Optional[float]]]:
    """The content of ``<reconstruct.metrics>/<name>.json``: the headline under ``reconstruct_<name>``, a key no
    other metrics file has (a test set may share the sequence's name)."""
    return {f"reconstruct_{name}": headline_measurement(result)}


def log_measurement(params: Params, project_root: Path, model_run_id: str, name: str, out_dir: Path,
                    result: dict) -> None:
    """Into the model's MLflow run (:func:`log_reconstruction`, with the reconstruction's files): the headline
    as metrics ``reconstruct/<name>/<figure>`` (columns of the runs table; figures that exist and are finite only,
    MLflow refuses NaN) and every figure as the table ``reconstruct/<name>/figures.csv``."""
    run = log_reconstruction(params, project_root, model_run_id, name, out_dir)
    headline = {f"reconstruct/{name}/{key}": value for key, value in headline_measurement(result).items()
                if value is not None and np.isfinite(value)}
    run.log_metrics(headline)
    run.show_in_runs_table(headline)
    run.log_table(measurement_rows(result), f"reconstruct/{name}/figures.csv")


def measurement_rows(result: dict) -> list[dict]:
    """Every measured figure, one row each: ``table`` (path or surface), ``row``, ``metric``, ``value``."""
    summary = metrics_summary(result)
    return [{"table": table, "row": row, "metric": metric, "value": value} for table in ("path", "surface")
            for row, figures in summary[table].items() for metric, value in figures.items()]


def format_measurement(name: str, result: dict) -> str:
    """Two small Markdown tables a person reads at the end of the stage: path and surface errors per row."""
    # the rows fuse at the ground truth's scale (measure_reconstruction): the voxel said is that one, which a
    # reader would otherwise take for the reconstruction's own
    lines = [f"## {name}: {result['frames']} frames, {result['frames_per_second']:.1f} frames/s; every surface "
             f"fused at the ground truth's scale, voxel {result['voxel_cm']:.3g} cm ({result['depth_scale']:.3g} "
             f"x the reconstruction's)", "",
             "| path | ATE RMSE cm | ATE median cm | RPE cm | RPE deg | scale | scale / depth's |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for row, figures in result["path"].items():
        over_depth = f"{figures['scale_over_depth']:.3f}" if "scale_over_depth" in figures else "–"
        lines.append(f"| {row} | {figures['ate_rmse']:.4f} | {figures['ate_median']:.4f} | "
                     f"{figures.get('rpe_trans', float('nan')):.4f} | {figures.get('rpe_rot', float('nan')):.3f} | "
                     f"{figures['scale']:.3f} | {over_depth} |")
    lines += ["", "| surface | accuracy mean / median cm | completeness mean / median cm | complete within "
                  f"{COMPLETE_WITHIN_VOXELS:g} voxels |", "| --- | --- | --- | --- |"]
    for row, figures in result["surface"].items():
        lines.append(f"| {row} | {_cm(figures['accuracy_mean'])} / {_cm(figures['accuracy_median'])} | "
                     f"{figures['completeness_mean']:.3f} / {figures['completeness_median']:.3f} | "
                     f"{figures['completeness_ratio']:.1%} |")
    return "\n".join(lines) + "\n"


def _cm(value: Optional[float]) -> str:
    return "none (empty mesh)" if value is None else f"{value:.3f}"
