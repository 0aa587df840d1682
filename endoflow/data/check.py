"""``endoflow data check``: does the ground truth explain the motion?

Warps sampled frames' neighbours into them with the ground-truth depth, pose and K, and flags a sequence whose
warp error (after a per-channel gain fit) is not well below the unwarped neighbour's. See docs/datasets.md,
"Ground-truth check".
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from endoflow.config import Params
from endoflow.data.base import Sequence
from endoflow.data.registry import open_reader
from endoflow.geometry.pose import relative_pose
from endoflow.geometry.warp import warp_frame

DEFAULT_MAX_RATIO = 0.7
DEFAULT_MAX_FRAMES = 10


def check_dataset(
    root: str | Path,
    dataset: Optional[str],
    params: Params,
    max_ratio: float = DEFAULT_MAX_RATIO,
    max_frames: int = DEFAULT_MAX_FRAMES,
) -> dict[str, Any]:
    """Check every sequence under ``root`` (``dataset`` None: detected from the layout).

    Returns a JSON-ready dict: ``ok`` (False when any sequence is flagged), ``dataset``, ``root``,
    ``max_ratio``, ``max_frames``, ``sequences`` (one entry per checked sequence, see
    :func:`check_sequence`) and ``skipped`` (sequences without RGB, depth or poses, with the reason).
    """
    reader = open_reader(root, dataset, params)
    checked, skipped = [], []
    for sequence in reader.sequences():
        missing = _missing_ground_truth(sequence)
        if missing:
            skipped.append({"name": sequence.name, "reason": missing})
        else:
            checked.append(check_sequence(sequence, max_ratio=max_ratio, max_frames=max_frames))
    return {
        "ok": not any(entry["flagged"] for entry in checked),
        "dataset": reader.name,
        "root": str(root),
        "max_ratio": max_ratio,
        "max_frames": max_frames,
        "sequences": checked,
        "skipped": skipped,
    }


def _missing_ground_truth(sequence: Sequence) -> str:
    absent = [
        what
        for what, present in (
            ("RGB frames", sequence.load_rgb is not None),
            ("depth", sequence.load_depth is not None),
            ("poses", sequence.poses is not None),
        )
        if not present
    ]
    return f"no {' or '.join(absent)}" if absent else ""


def _is_adjacent(sequence: Sequence, target: int, source: int, step: int) -> bool:
    """``source`` is the frame right beside ``target`` (``step`` apart): inside the sequence, none missing between."""
    return 0 <= source < len(sequence) and abs(sequence.frame_ids[source] - sequence.frame_ids[target]) == step


def check_sequence(
    sequence: Sequence, max_ratio: float = DEFAULT_MAX_RATIO, max_frames: int = DEFAULT_MAX_FRAMES
) -> dict[str, Any]:
    """GT warp error against identity error for one sequence that has RGB, depth and poses.

    Returns ``name``, ``split``, ``pairs`` (target-neighbour pairs measured), ``gt_error`` and
    ``identity_error`` (gain-compensated, means over pairs), ``ratio`` (their quotient, what is judged),
    ``plain_gt_error``, ``plain_identity_error``, ``plain_ratio`` (the same without gain compensation),
    ``valid_fraction`` (share of target pixels with depth that land inside the neighbour),
    ``frames_without_pose`` (skipped frames: no pose, or a non-finite one), ``flagged`` and ``reason``.
    """
    frames = _FrameCache(sequence)
    step = sequence.frame_step
    measured = [
        _pair_errors(frames, sequence, target, source)
        for target in _sample_targets(sequence, max_frames)
        for source in (target + 1, target - 1)
        if _is_adjacent(sequence, target, source, step) and sequence.pose(source) is not None
    ]
    with_pixels = [pair for pair in measured if pair.errors is not None]
    means = np.mean([pair.errors for pair in with_pixels], axis=0) if with_pixels else [None] * 4
    gt, identity, plain_gt, plain_identity = (None if m is None else float(m) for m in means)
    result = {
        "name": sequence.name,
        "split": sequence.split,
        "pairs": len(measured),
        "gt_error": gt,
        "identity_error": identity,
        "ratio": None,
        "plain_gt_error": plain_gt,
        "plain_identity_error": plain_identity,
        "plain_ratio": plain_gt / plain_identity if with_pixels and plain_identity > 0 else None,
        "valid_fraction": float(np.mean([pair.valid_fraction for pair in measured])) if measured else 0.0,
        "frames_without_pose": sum(sequence.pose(i) is None for i in range(len(sequence))),
    }
    return {**result, **_verdict(result, max_ratio)}


def _verdict(result: dict[str, Any], max_ratio: float) -> dict[str, Any]:
    if not result["pairs"]:
        return {"flagged": True, "reason": "no pair of consecutive frames with known poses"}
    if result["gt_error"] is None:
        return {"flagged": True, "reason": "no pixel with depth lands inside the neighbour under the GT pose"}
    if result["identity_error"] == 0:
        return {"flagged": False, "reason": "frames do not change: nothing to check"}
    ratio = result["gt_error"] / result["identity_error"]
    if ratio > max_ratio:
        reason = (f"GT warp error is {ratio:.2f} of the identity error (> {max_ratio}): "
                  "check K, pose handedness and direction, depth units")
        return {"ratio": ratio, "flagged": True, "reason": reason}
    return {"ratio": ratio, "flagged": False, "reason": ""}


def _sample_targets(sequence: Sequence, max_frames: int) -> list[int]:
    with_pose = [i for i in range(len(sequence)) if sequence.pose(i) is not None]
    if len(with_pose) <= max_frames:
        return with_pose
    picks = np.linspace(0, len(with_pose) - 1, max_frames).round().astype(int)
    return [with_pose[i] for i in picks]


class _FrameCache:
    """Decodes each frame once: neighbours of one target are targets or neighbours of the next."""

    def __init__(self, sequence: Sequence) -> None:
        self.sequence = sequence
        self.rgb: dict[int, torch.Tensor] = {}
        self.depth: dict[int, torch.Tensor] = {}
        self.in_view = torch.from_numpy(sequence.field_of_view())[None].float()  # the endoscope's circle

    def image(self, i: int) -> torch.Tensor:
        if i not in self.rgb:
            rgb = self.sequence.load_rgb(i)
            self.rgb[i] = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div(255)
        return self.rgb[i]

    def depth_cm(self, i: int) -> torch.Tensor:
        if i not in self.depth:
            self.depth[i] = torch.from_numpy(np.asarray(self.sequence.load_depth(i), dtype=np.float32))[None]
        return self.depth[i]


@dataclass
class _PairErrors:
    """(gt, identity, plain gt, plain identity) mean absolute errors, None where no pixel is comparable."""

    errors: Optional[tuple[float, float, float, float]]
    valid_fraction: float


def _pair_errors(frames: _FrameCache, sequence: Sequence, target: int, source: int) -> _PairErrors:
    image_t, image_s, depth_t = frames.image(target), frames.image(source), frames.depth_cm(target)
    T_s_t = relative_pose(sequence.pose(source), sequence.pose(target))
    warped, valid = warp_frame(
        image_s[None],
        depth_t[None],
        torch.as_tensor(T_s_t, dtype=torch.float32)[None],
        torch.as_tensor(sequence.K, dtype=torch.float32)[None],
    )
    # only pixels in the field of view whose sample lands in it: a black border matches itself without a warp
    lands_in_view = warp_frame(frames.in_view[None], depth_t[None], torch.as_tensor(T_s_t, dtype=torch.float32)[None],
                               torch.as_tensor(sequence.K, dtype=torch.float32)[None])[0][0] > 0.999
    has_depth = (depth_t > 0) & (frames.in_view > 0)
    mask = (valid[0] & has_depth & lands_in_view).float()
    count = float(mask.sum())
    valid_fraction = count / max(float(has_depth.sum()), 1.0)
    if count == 0:
        return _PairErrors(None, valid_fraction)
    warped = warped[0]
    errors = (
        _masked_error(_gain_fitted(warped, image_t, mask), image_t, mask),
        _masked_error(_gain_fitted(image_s, image_t, mask), image_t, mask),
        _masked_error(warped, image_t, mask),
        _masked_error(image_s, image_t, mask),
    )
    return _PairErrors(errors, valid_fraction)


def _gain_fitted(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``image`` times the per-channel gain minimising ``sum(mask * (gain * image - target)^2)``."""
    gain = (image * target * mask).sum((1, 2)) / (image * image * mask).sum((1, 2)).clamp(min=1e-12)
    return image * gain[:, None, None]


def _masked_error(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean absolute error over the channels and the pixels where ``mask`` is 1."""
    return float(((image - target).abs() * mask).sum()) / (image.shape[0] * float(mask.sum()))


def format_check(report: dict[str, Any]) -> str:
    """Human-readable table of :func:`check_dataset`'s report."""
    lines = [
        f"{report['dataset']} at {report['root']}: GT warp error / identity-pose error per sequence, "
        f"gain-compensated (plain: without), flagged above {report['max_ratio']}; "
        f"up to {report['max_frames']} target frames each",
        f"  {'sequence':<24} {'split':<6} {'pairs':>5} {'gt err':>8} {'id err':>8} {'ratio':>6} "
        f"{'plain':>6} {'valid':>6}  verdict",
    ]
    for entry in report["sequences"]:
        if entry["flagged"]:
            verdict = f"FLAGGED: {entry['reason']}"
        else:
            verdict = f"ok ({entry['reason']})" if entry["reason"] else "ok"
        lines.append(
            f"  {entry['name']:<24} {entry['split']:<6} {entry['pairs']:>5} {_number(entry['gt_error'], 4):>8} "
            f"{_number(entry['identity_error'], 4):>8} {_number(entry['ratio'], 2):>6} "
            f"{_number(entry['plain_ratio'], 2):>6} {entry['valid_fraction']:>6.0%}  {verdict}"
        )
        if entry["frames_without_pose"]:
            lines.append(f"  {'':<24} {entry['frames_without_pose']} frame(s) without a valid pose skipped")
    for entry in report["skipped"]:
        lines.append(f"  {entry['name']:<24} skipped: {entry['reason']}")
    flagged = sum(entry["flagged"] for entry in report["sequences"])
    checked = len(report["sequences"])
    if report["ok"]:
        lines.append(f"OK: {checked} sequence(s) checked, none flagged, {len(report['skipped'])} skipped")
    else:
        lines.append(f"FAILED: {flagged} of {checked} checked sequence(s) flagged")
    return "\n".join(lines)


def _number(value: Optional[float], digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"
