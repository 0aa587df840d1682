"""The path refinement (``KeyframeTracker``) of an earlier version of the code against this one, in one run.

    python benchmarks/bench_tracker.py --baseline DIR [--sizes 64 256 480] [--frames 12] [--threads 2] [--device cpu]
                                       [--model FILE] [--rounds 1]

``DIR`` holds an earlier ``endoflow`` package (``git archive <commit> endoflow | tar -x -C DIR``). For each size,
sequence S1 of a synthetic SimCol3D layout is rendered once by this tree (``--frames`` frames with their exact depth,
intrinsics and poses). Each version then tracks it in a fresh process with ``--threads`` torch threads, the
default ``refine`` params and the frames on ``--device`` (``cuda``: a GPU, waited for before the clock stops): every
frame from the previous refined pose times the previous refined step (constant velocity; the first step from the
truth), aligned to the keyframes with the exact depth, or with ``--model``'s depth (this tree's networks in float32
on the CPU: a trained model's depth is wrong in shape, and there the tracker works harder). One untimed pass, then a
timed one; with ``--rounds`` > 1 the versions alternate, so that load from other processes hits them alike, and
the median is printed. Printed per size: ms a tracked frame of each version and their ratio, how far this tree's
steps are from the earlier one's (translation relative to the step's length, rotation in degrees, the largest over
the frames), and each version's mean step errors against the truth (translation in cm, rotation in degrees).
Figures are printed, not asserted.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from code_versions import environment_importing

ROOT = Path(__file__).resolve().parents[1]
VERSIONS = ("before", "after")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="folder holding the earlier endoflow package")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 480])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="where the frames are: cpu or cuda")
    parser.add_argument("--model", type=Path, help="track with this trained model's depth (default: the exact one)")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--worker", nargs=2, metavar=("INPUTS", "OUT"), help=argparse.SUPPRESS)
    return parser.parse_args()


def make_inputs(folder: Path, size: int, frames: int, threads: int, model: Path | None) -> Path:
    """S1 rendered at ``size`` px: its frames ``[N, 3, H, W]`` in [0, 1], depth ``[N, 1, H, W]`` in cm (exact, or
    ``model``'s), ``K`` and camera-to-world poses, saved as plain tensors for both versions to read."""
    import torch

    from endoflow.config import Params
    from endoflow.data.registry import open_reader
    from endoflow.synth.writers import synthesize_layout

    params = Params()
    root = folder / f"scene{size}"
    synthesize_layout("simcol", root, sequences=1, frames=frames, size=size, seed=0, params=params,
                      workers=threads, device="cpu")
    sequence = next(s for s in open_reader(root, None, params).sequences() if s.name == "S1")
    path = folder / f"inputs{size}.pt"
    rgb = torch.from_numpy(np.stack([sequence.load_rgb(i) for i in range(len(sequence))])).permute(0, 3, 1, 2)
    depth = (predicted_depth(model, rgb) if model else
             torch.from_numpy(np.stack([sequence.load_depth(i) for i in range(len(sequence))]))[:, None])
    torch.save({"rgb": rgb.double() / 255, "depth": depth, "K": torch.from_numpy(sequence.K),
                "poses": torch.from_numpy(np.stack(sequence.poses))}, path)
    return path


def predicted_depth(model_file: Path, rgb: torch.Tensor) -> torch.Tensor:
    """``[N, 1, H, W]`` cm: the model's depth of 8-bit frames ``rgb [N, 3, H, W]``, one at a time, as
    ``reconstruct`` predicts it on a CPU in float32."""
    import torch

    from endoflow.devices import images_to_device, to_compute_layout
    from endoflow.models.endoflow_model import load_trained_model

    cpu = torch.device("cpu")
    model, _ = load_trained_model(model_file, cpu)
    model = to_compute_layout(model, cpu, "float32", rgb.shape[-1])
    with torch.no_grad():
        return torch.cat([model.predict_depth(images_to_device(frame[None].contiguous(), cpu, "float32")).float()
                          for frame in rgb])


def run_worker(inputs: Path, out: Path, threads: int, device: str) -> None:
    """Track the inputs with whichever endoflow this process's PYTHONPATH names; write the poses and the time."""
    import torch

    from endoflow.config import Params
    from endoflow.geometry.direct_alignment import KeyframeTracker, tracker_settings

    torch.set_num_threads(threads)
    data = torch.load(inputs, weights_only=True)
    rgbs, depths = data["rgb"].to(device), data["depth"].to(device)

    def track() -> list[np.ndarray]:
        tracker = KeyframeTracker(data["K"], tracker_settings(Params().refine))
        truth = data["poses"].double()
        # poses on the CPU whatever a version returns (an earlier one returned them on the frames' device)
        poses = [tracker.track(rgbs[0], depths[0], truth[0]).cpu()]
        step = torch.linalg.inv(truth[0]) @ truth[1]
        for rgb, depth in zip(rgbs[1:], depths[1:]):
            poses.append(tracker.track(rgb, depth, poses[-1] @ step).cpu())
            step = torch.linalg.inv(poses[-2]) @ poses[-1]
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        return [pose.numpy() for pose in poses]

    track()
    started = time.perf_counter()
    poses = track()
    seconds = time.perf_counter() - started
    out.write_text(json.dumps({"ms_per_frame": 1e3 * seconds / (len(poses) - 1),
                               "poses": [pose.tolist() for pose in poses]}))


def step_differences(reference: np.ndarray, other: np.ndarray) -> tuple[float, float]:
    """Largest translation difference relative to the reference step's length, and rotation difference (deg)."""
    from endoflow.evaluation.metrics import relative_poses
    from endoflow.geometry.pose import rotation_angle_deg

    a, b = relative_poses(reference), relative_poses(other)
    translation = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1) / np.linalg.norm(a[:, :3, 3], axis=1)
    rotation = rotation_angle_deg(np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3])
    return float(translation.max()), float(rotation.max())


def step_errors(truth: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """Mean step errors against the truth: translation (cm) and rotation (deg)."""
    from endoflow.evaluation.metrics import relative_poses
    from endoflow.geometry.pose import rotation_angle_deg

    error = np.linalg.inv(relative_poses(truth)) @ relative_poses(poses)
    return float(np.linalg.norm(error[:, :3, 3], axis=1).mean()), float(rotation_angle_deg(error[:, :3, :3]).mean())


def main() -> None:
    args = parse_args()
    if args.worker:
        run_worker(Path(args.worker[0]), Path(args.worker[1]), args.threads, args.device)
        return
    if args.model and not args.model.is_file():
        raise SystemExit(f"{args.model}: no such model file")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_tracker_") as folder:
        work = Path(folder)
        for size in args.sizes:
            inputs = make_inputs(work, size, args.frames, args.threads, args.model)
            results: dict[str, list[dict]] = {version: [] for version in VERSIONS}
            for _ in range(args.rounds):
                for version in VERSIONS:
                    tree = args.baseline.resolve() if version == "before" else ROOT
                    out = work / f"{version}{size}.json"
                    command = [sys.executable, __file__, "--baseline", str(args.baseline), "--threads",
                               str(args.threads), "--device", args.device, "--worker", str(inputs), str(out)]
                    subprocess.run(command, env=environment_importing(tree), check=True)
                    results[version].append(json.loads(out.read_text()))
                    print(f"{size} px {version:6s} {results[version][-1]['ms_per_frame']:8.1f} ms a tracked frame",
                          flush=True)
            import torch

            truth = torch.load(inputs, weights_only=True)["poses"].double().numpy()
            before, after = (np.array(results[v][0]["poses"]) for v in VERSIONS)  # the same in every round
            rows.append((size, *(statistics.median(run["ms_per_frame"] for run in results[v]) for v in VERSIONS),
                         *step_differences(before, after), *step_errors(truth, before), *step_errors(truth, after)))
    depth = f"the depth of {args.model}" if args.model else "exact depth"
    print(f"\nKeyframeTracker, {args.frames} rendered frames with {depth}, {args.threads} torch threads, frames on "
          f"{args.device}, median of {args.rounds} round(s); before: {args.baseline}")
    print(f"{'size':>5s} {'before ms':>10s} {'after ms':>9s} {'before/after':>13s} {'steps: d trans':>15s} "
          f"{'d rot (deg)':>12s} {'error before: cm':>17s} {'deg':>7s} {'after: cm':>10s} {'deg':>7s}")
    for size, slow, fast, d_trans, d_rot, t_before, r_before, t_after, r_after in rows:
        print(f"{size:5d} {slow:10.1f} {fast:9.1f} {slow / fast:13.2f} {d_trans:15.1e} {d_rot:12.1e} "
              f"{t_before:17.5f} {r_before:7.4f} {t_after:10.5f} {r_after:7.4f}")
    if any(math.isnan(value) for row in rows for value in row):
        print("(nan: a step of length 0)")


if __name__ == "__main__":
    main()
