"""What the path refinement's finest level (``refine.max_size``) costs and gives at 480 px, in one run.

    python benchmarks/bench_refine_size.py --model FILE [--max-sizes 0 240 120] [--frames 60] [--rounds 1]
                                           [--threads 2] [--precision float32|bf16]

Sequence S1 of a synthetic SimCol3D layout is rendered once at 480 px (``--frames`` frames with their exact poses).
For each of ``--max-sizes`` (0: full resolution, the default ``null``) a fresh process with ``--threads`` torch
threads runs the whole ``reconstruct()`` call of ``FILE`` (a trained model: an untrained one's depth is nearly flat)
at 480 px on the CPU: fused, the path refined with the default ``refine`` params but for ``max_size``, every output
written, after an untimed 3-frame warm-up call. With ``--rounds`` > 1 the sizes alternate, so that load from other
processes hits them alike, and the median rate is printed. Printed per size: frames/s of the call and its ratio to
the first size's, and the written path's errors against the truth after a Sim(3) alignment (``evo`` RPE between
consecutive frames in cm and degrees, ATE RMSE in cm); then the pose network's own chain, the same in every call.
Figures are printed, not asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIZE = 480
WARM_UP_FRAMES = 3
ERRORS = ("rpe_trans", "rpe_rot", "ate_rmse")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="a trained model file (endoflow.pt)")
    parser.add_argument("--max-sizes", type=int, nargs="+", default=[0, 240, 120],
                        help="refine.max_size of each call, px; 0: full resolution")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--precision", choices=("float32", "bf16"), default="float32")
    parser.add_argument("--worker", nargs=3, metavar=("SCENE", "MAX_SIZE", "OUT"), help=argparse.SUPPRESS)
    return parser.parse_args()


def render_scene(work: Path, frames: int, threads: int) -> Path:
    from endoflow.config import Params
    from endoflow.synth.writers import synthesize_layout

    print(f"rendering {frames} frames at {SIZE} px", file=sys.stderr, flush=True)
    synthesize_layout("simcol", work / "scene", sequences=1, frames=frames, size=SIZE, seed=0, params=Params(),
                      workers=threads, device="cpu")
    return work / "scene"


def run_worker(args: argparse.Namespace) -> dict:
    """One call at one ``max_size``: its rate, and the errors of the refined and the network's paths."""
    from endoflow.config import Params
    from endoflow.data.trajectory_files import read_tum
    from endoflow.devices import use_cpu_threads
    from endoflow.geometry.direct_alignment import tracker_settings
    from endoflow.reconstruction.frames import FrameRange, open_frames
    from endoflow.reconstruction.measure import path_errors
    from endoflow.reconstruction.reconstruct import NETWORK_PATH_FILE, ReconstructOptions, reconstruct

    use_cpu_threads(args.threads)
    scene, max_size, out = Path(args.worker[0]), int(args.worker[1]), Path(args.worker[2])
    params = Params()
    source = open_frames(scene, "S1", params)
    refine = tracker_settings(params.refine.replace(max_size=max_size or None))

    def call(frames: FrameRange, folder: Path) -> dict:
        options = ReconstructOptions(frames=frames, size=SIZE, device="cpu", refine=refine, precision=args.precision)
        with open(os.devnull, "w") as nowhere, contextlib.redirect_stderr(nowhere):
            return reconstruct(source, source.K, args.model, folder, options)

    call(FrameRange(stop=WARM_UP_FRAMES), out / "warm-up")
    started = time.perf_counter()
    summary = call(FrameRange(), out / "timed")
    seconds = time.perf_counter() - started
    truth = source.sequence.poses
    errors = {}
    for name, file in (("refined", "trajectory.tum"), ("network", NETWORK_PATH_FILE)):
        measured = path_errors(truth, read_tum(out / "timed" / file)[1], with_scale=True)
        errors[name] = {key: measured[key] for key in ERRORS}
    return {"frames_per_s": summary["frames"] / seconds, **errors}


def run_size(args: argparse.Namespace, scene: Path, max_size: int, out: Path) -> dict:
    command = [sys.executable, __file__, "--model", str(args.model), "--threads", str(args.threads),
               "--precision", args.precision, "--worker", str(scene), str(max_size), str(out)]
    done = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if done.returncode:
        raise SystemExit(f"max_size {max_size} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    args = parse_args()
    if args.worker:
        print(json.dumps(run_worker(args)))
        return
    if not args.model.is_file():
        raise SystemExit(f"{args.model}: no such model file")
    runs: dict[int, list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_refine_size_") as folder:
        work = Path(folder)
        scene = render_scene(work, args.frames, args.threads)
        for round_index in range(args.rounds):
            for max_size in args.max_sizes:
                run = run_size(args, scene, max_size, work / f"out{max_size}-{round_index}")
                runs.setdefault(max_size, []).append(run)
                print(f"round {round_index + 1}/{args.rounds} max_size {max_size or 'full':>5} "
                      f"{run['frames_per_s']:6.2f} frames/s", flush=True)
    print(f"\nreconstruct at {SIZE} px, fused, path refined; {args.frames} frames of S1, {args.threads} torch threads, "
          f"{args.precision}, {args.rounds} round(s); model: {args.model}")
    print(f"{'max_size':>8s} {'frames/s':>9s} {'x first':>8s} {'RPE cm':>9s} {'RPE deg':>8s} {'ATE cm':>8s}")
    first = statistics.median(run["frames_per_s"] for run in runs[args.max_sizes[0]])
    for max_size in args.max_sizes:
        rate = statistics.median(run["frames_per_s"] for run in runs[max_size])
        refined = runs[max_size][0]["refined"]  # the first round's path
        print(f"{max_size or 'full':>8} {rate:9.2f} {rate / first:8.2f} {refined['rpe_trans']:9.5f} "
              f"{refined['rpe_rot']:8.4f} {refined['ate_rmse']:8.4f}")
    network = runs[args.max_sizes[0]][0]["network"]
    print(f"{'network':>8s} {'':9s} {'':8s} {network['rpe_trans']:9.5f} {network['rpe_rot']:8.4f} "
          f"{network['ate_rmse']:8.4f}   (the pose network's chain, not refined)")


if __name__ == "__main__":
    main()
