"""``endoflow data inspect``: what a reader understood of a dataset root, as a dict and as text.

Only a few frames per sequence are decoded (first, middle, last by default), so inspecting a full dataset
stays quick; a frame that fails to decode is reported as a problem of its sequence rather than aborting.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Optional

import numpy as np

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.layout import shown_numbers
from endoflow.data.registry import open_reader
from endoflow.errors import DataFormatError
from endoflow.geometry.pose import motion_statistics

DEFAULT_SAMPLED_FRAMES = 3


def inspect_dataset(
    root: str | Path, dataset: Optional[str], params: Params, sampled_frames: int = DEFAULT_SAMPLED_FRAMES
) -> dict[str, Any]:
    """Summary of every sequence under ``root`` (``dataset`` None: detected from the layout).

    Returns a JSON-ready dict: ``dataset``, ``root``, ``frames_per_split`` and ``sequences``, each with
    ``name``, ``split``, ``group``, ``frames``, ``frame_ids`` (first, last), ``image_size`` [H, W], ``K``
    (3x3), ``rgb`` (whether frames have colour), ``depth_cm`` (``min`` over readings > 0, ``max``,
    ``no_reading_fraction``, ``sampled_frames``; None without depth), ``poses`` (``known`` count, ``unknown``
    frame numbers, ``first`` and ``last`` known ``{frame, T_world_cam}``, converted to our convention; None
    without poses) and ``problems`` (the reader's: frame gaps, NaN or inf in pose files with the frames,
    pose alignment; and frames that fail to decode).
    """
    reader = open_reader(root, dataset, params)
    # Readers warn about pose alignment; the same notes are in each sequence's problems, shown below.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sequences = reader.sequences()
    entries = [inspect_sequence(sequence, sampled_frames) for sequence in sequences]
    per_split: dict[str, int] = {}
    for entry in entries:
        per_split[entry["split"]] = per_split.get(entry["split"], 0) + entry["frames"]
    return {"dataset": reader.name, "root": str(root), "frames_per_split": per_split, "sequences": entries}


def inspect_sequence(sequence: Sequence, sampled_frames: int = DEFAULT_SAMPLED_FRAMES) -> dict[str, Any]:
    """One sequence's entry of :func:`inspect_dataset` (decodes ``sampled_frames`` evenly spaced frames)."""
    positions = sorted({int(round(p)) for p in np.linspace(0, len(sequence) - 1, max(sampled_frames, 1))})
    problems = list(sequence.problems)
    depths = []
    for i in positions:
        try:
            if sequence.load_rgb is not None:
                sequence.load_rgb(i)
            if sequence.load_depth is not None:
                depths.append(sequence.load_depth(i))
        except DataFormatError as exc:
            problems.append(f"frame {sequence.frame_ids[i]}: {exc}")
    return {
        "name": sequence.name,
        "split": sequence.split,
        "group": sequence.group,
        "frames": len(sequence),
        "frame_ids": [sequence.frame_ids[0], sequence.frame_ids[-1]],
        "image_size": list(sequence.image_size),
        "K": np.asarray(sequence.K).tolist(),
        "rgb": sequence.load_rgb is not None,
        "depth_cm": _depth_summary(depths, [sequence.frame_ids[i] for i in positions])
        if sequence.load_depth is not None
        else None,
        "poses": _pose_summary(sequence),
        "problems": problems,
    }


def _depth_summary(depths: list[np.ndarray], frame_ids: list[int]) -> Optional[dict[str, Any]]:
    if not depths:
        return None
    values = np.concatenate([d.ravel() for d in depths])
    readings = values[values > 0]
    return {
        "min": float(readings.min()) if readings.size else None,
        "max": float(readings.max()) if readings.size else None,
        "no_reading_fraction": float(1 - readings.size / values.size),
        "sampled_frames": frame_ids,
    }


def _pose_summary(sequence: Sequence) -> Optional[dict[str, Any]]:
    if sequence.poses is None:
        return None
    known = [i for i in range(len(sequence)) if sequence.pose(i) is not None]
    unknown = sorted(set(range(len(sequence))) - set(known))

    def entry(i: int) -> dict[str, Any]:
        return {"frame": sequence.frame_ids[i], "T_world_cam": sequence.poses[i].tolist()}

    return {
        "known": len(known),
        "unknown": [sequence.frame_ids[i] for i in unknown],
        "first": entry(known[0]) if known else None,
        "last": entry(known[-1]) if known else None,
        # per-frame motion, where every frame has a pose (a gap would make two frames' motion one step)
        "motion": motion_statistics(sequence.poses) if not unknown and len(known) >= 3 else None,
    }


def format_inspection(report: dict[str, Any]) -> str:
    """Readable text of an :func:`inspect_dataset` report."""
    splits = ", ".join(f"{split} {count}" for split, count in sorted(report["frames_per_split"].items()))
    lines = [
        f"{report['dataset']} at {report['root']}: {len(report['sequences'])} sequence(s); frames per split: {splits}"
    ]
    for entry in report["sequences"]:
        lines += [""] + _format_sequence(entry)
    return "\n".join(lines)


def _format_sequence(entry: dict[str, Any]) -> list[str]:
    height, width = entry["image_size"]
    first, last = entry["frame_ids"]
    lines = [
        f"{entry['name']}  [split {entry['split']}, group {entry['group'] or '-'}]  "
        f"{entry['frames']} frames ({first}..{last}), {width}x{height}{'' if entry['rgb'] else ', no RGB'}",
        "  K (pixels, stored size):",
        *_format_rows(entry["K"], indent=4),
    ]
    depth = entry["depth_cm"]
    if depth is None:
        lines.append("  depth: none")
    elif depth["min"] is None:
        lines.append(f"  depth: no readings in frames {depth['sampled_frames']}")
    else:
        lines.append(
            f"  depth (frames {', '.join(map(str, depth['sampled_frames']))}): {depth['min']:.4g} .. "
            f"{depth['max']:.4g} cm, {100 * depth['no_reading_fraction']:.1f}% without reading"
        )
    poses = entry["poses"]
    if poses is None:
        lines.append("  poses: none")
    else:
        unknown = f"; unknown: frames {shown_numbers(poses['unknown'])}" if poses["unknown"] else ""
        lines.append(
            f"  poses: {poses['known']} of {entry['frames']} frames known{unknown} (T_world_cam: OpenCV, cm)"
        )
        if poses.get("motion"):
            motion = poses["motion"]
            lines.append(f"    motion per frame (medians): step {motion['step_mm']:.3f} mm, rotation "
                         f"{motion['rotation_deg']:.3f} deg; change from the last step {motion['step_change_mm']:.4f} "
                         f"mm, {motion['rotation_change_deg']:.4f} deg; {100 * motion['forward_share']:.0f}% "
                         "forward")
        for label in ("first", "last"):
            if poses[label] is not None:
                lines.append(f"    {label} known, frame {poses[label]['frame']} (top 3 rows):")
                lines += _format_rows(poses[label]["T_world_cam"][:3], indent=6)
    lines.append("  problems: " + ("none" if not entry["problems"] else ""))
    lines += [f"    - {problem}" for problem in entry["problems"]]
    return lines


def _format_rows(matrix: list[list[float]], indent: int) -> list[str]:
    return [" " * indent + " ".join(f"{value:12.6f}" for value in row) for row in matrix]
