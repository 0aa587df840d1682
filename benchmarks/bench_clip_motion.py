"""What a model made of a video without ground truth: whether its path moves as a camera does and whether its depth
changes with the frames, read from `endoflow reconstruct` output folders.

    endoflow reconstruct colonoscopy.mp4 --model <model> --out <folder> [--no-refine --no-fusion ...]
    python benchmarks/bench_clip_motion.py <folder> [<folder> ...] [--window 50]

Per folder, one row:

- from ``trajectory.tum``: the share of steps ``inv(P_i) @ P_{i+1}`` that go forward (along the earlier camera's
  view, as ``motion_statistics`` counts them), the net advance (the sum of those forward components, cm in the
  model's unit), the share of ``--window``-frame windows whose steps add up to a forward advance, and the step
  length's coefficient of variation (0 for a constant step);
- from ``reconstruction.json``: the photometric error along the written path (lower explains the frames better);
- from ``depth/*.png``: how much the depth changes from frame to frame, as the median over the pixels in view of
  every frame of the standard deviation of log depth over the frames, and the mean correlation of a frame's log
  depth with the run's mean log-depth map (1: one map for every frame, what a depth network that ignores its input
  would give).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from endoflow.data.imageio import read_gray16
from endoflow.errors import DataFormatError
from endoflow.data.trajectory_files import read_tum
from endoflow.geometry.pose import motion_statistics, relative_pose


def path_figures(folder: Path, window: int) -> dict[str, float]:
    """The path's figures of the module docstring, from ``folder/trajectory.tum``."""
    _, T_world_cam = read_tum(folder / "trajectory.tum")
    if len(T_world_cam) < 3:
        raise DataFormatError(folder / "trajectory.tum", f"expected 3 or more poses, found {len(T_world_cam)}")
    translation = relative_pose(T_world_cam[:-1], T_world_cam[1:])[:, :3, 3]
    forward = translation[:, 2]
    length = np.linalg.norm(translation, axis=1)
    windows = forward[: len(forward) // window * window].reshape(-1, window).sum(axis=1)
    return {"forward_share": motion_statistics(T_world_cam)["forward_share"], "net_advance_cm": float(forward.sum()),
            "windows_forward": float(np.mean(windows > 0)) if windows.size else float("nan"),
            "step_variation": float(length.std() / length.mean())}


def depth_figures(folder: Path) -> dict[str, float]:
    """The depth's figures of the module docstring, from ``folder/depth/*.png`` (0: out of view)."""
    paths = sorted((folder / "depth").glob("*.png"))
    counts = np.stack([read_gray16(path) for path in paths]) if len(paths) >= 2 else None
    in_view = (counts > 0).all(axis=0) if counts is not None else None
    if in_view is None or not in_view.any():
        raise DataFormatError(folder / "depth", "expected two or more depth maps sharing pixels in view")
    log_depth = np.log(counts[:, in_view].astype(np.float64))  # the unit only shifts log depth: it drops out
    mean_map = log_depth.mean(axis=0)
    return {"depth_spread": float(np.median(log_depth.std(axis=0))),
            "mean_map_correlation": float(np.mean([np.corrcoef(frame, mean_map)[0, 1] for frame in log_depth]))}


def photometric_error(folder: Path) -> float:
    """The photometric error along the written path, from ``folder/reconstruction.json``."""
    summary = folder / "reconstruction.json"
    try:
        return float(json.loads(summary.read_text())["path"]["photometric_error"]["path"])
    except (KeyError, TypeError, json.JSONDecodeError) as error:
        raise DataFormatError(summary, f"expected endoflow reconstruct's JSON with path.photometric_error.path "
                                       f"({type(error).__name__}: {error})") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+", help="endoflow reconstruct output folders")
    parser.add_argument("--window", type=int, default=50, help="frames per window of the windows' forward share")
    args = parser.parse_args()
    if args.window < 1:
        parser.error(f"--window {args.window}: expected at least 1 frame")
    rows = []
    for folder in args.folders:
        try:
            rows.append((folder, path_figures(folder, args.window), depth_figures(folder), photometric_error(folder)))
        except (DataFormatError, ValueError, OSError) as problem:
            raise SystemExit(f"bench_clip_motion: {problem}") from None
    print("| folder | steps forward | net advance (cm, model's unit) | windows forward | step's coefficient of "
          "variation | photometric error | depth's spread over frames (log) | correlation with its mean map |")
    print("| --- " * 8 + "|")
    for folder, path, depth, error in rows:
        print(f"| {folder} | {path['forward_share']:.1%} | {path['net_advance_cm']:+.2f} | "
              f"{path['windows_forward']:.0%} | {path['step_variation']:.2f} | {error:.4f} | "
              f"{depth['depth_spread']:.3f} | {depth['mean_map_correlation']:.3f} |")


if __name__ == "__main__":
    main()
