"""TSDF fusion alone: its speed at 480 px (the compiled CPU loops against the tensor code, in one process) and its
floor (exact depth on the exact path, against the renderer's surface), for this tree and, with ``--baseline``, an
earlier one.

    python benchmarks/bench_fusion.py [--baseline DIR] [--frames 12] [--threads 2] [--rounds 3] [--device cpu|cuda]

``DIR`` holds an earlier ``endoflow`` package (``git archive <commit> endoflow | tar -x -C DIR``); the same
measurement runs in a child process importing it. Both scenes are rendered by the built-in renderer (sequence S1
of a SimCol3D layout, seed 1) with their exact depth, so the fusion has a real surface to fuse:

- **speed**: ``--frames`` frames at 480 px, the voxel ``reconstruct`` picked there until it followed the depth
  (``max_depth / 4 / fx``, fixed so that figures compare across commits), truncation 4 voxels; milliseconds a
  frame to integrate (the median of ``--rounds`` fusions of all frames, each into a new volume, so the volume's
  growth is counted), and the seconds to extract the mesh, by each extraction the tree has (scikit-image's on
  the host; the volume's own marching cubes on its device, ``extract_mesh_on_device``). Where the tree has
  both integrations (``TSDFVolume(compiled=...)``) and the volume lives on the CPU, both run on the same frames and
  the volumes are compared to the bit. ``--device cuda`` fuses and meshes on the GPU (the tensor code).
- **floor**: ``--frames`` frames at 64 px, voxel 0.15 cm (``tests/test_reconstruct_measure.py``'s scene and voxel),
  at truncations of 4 (the default), 3 and 2 voxels: how far the mesh's vertices lie from the ground truth
  (median, 75th and 90th percentile, cm; the share farther than 2 voxels) and the share of the ground truth within 2
  voxels of the mesh (``completeness_ratio``), as the reconstruct stage measures them; with each extraction the
  tree has (on the CPU).

Figures are printed, not asserted.
"""

from __future__ import annotations

import argparse
import inspect
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from code_versions import environment_importing

ROOT = Path(__file__).resolve().parents[1]
FLOOR_VOXEL_CM = 0.15
TRUNCATIONS = (4, 3, 2)  # voxels


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, default=None, help="folder holding an earlier endoflow package")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="where the speed part's volume lives")
    parser.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    return parser.parse_args()


def rendered_frames(frames: int, size: int) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """K at ``size`` and each frame's (exact depth, RGB, T_world_cam) of sequence S1, rendered at ``size``."""
    from endoflow.data.frame_encoding import resize_depth, resize_rgb, stored_intrinsics
    from endoflow.reconstruction.frames import DatasetFrames, FrameRange
    from endoflow.synth.writers import synthesize_layout
    from tests.small_model import small_model_params

    params = small_model_params(64)
    with tempfile.TemporaryDirectory(prefix="bench_fusion_") as folder:
        root = Path(folder) / "SimCol3D"
        synthesize_layout("simcol", root, sequences=1, frames=frames, size=size, seed=1, params=params, workers=1,
                          device="cpu")
        source = DatasetFrames(root, "S1", params)
        K = stored_intrinsics(source.K, source.native_size, size)
        return K, [(resize_depth(frame.depth_cm.astype(np.float32), size), resize_rgb(frame.rgb, size),
                    frame.T_world_cam) for frame in source.frames(FrameRange())]


def fused(K: np.ndarray, frames: list, voxel_cm: float, trunc_cm: float, **options):
    from endoflow.reconstruction.fusion import TSDFVolume

    volume = TSDFVolume(voxel_cm, trunc_cm, **options)
    for depth, rgb, T_world_cam in frames:
        volume.integrate(depth, rgb, K, T_world_cam)
    return volume


def extractions(volume) -> dict:
    """The mesh extractions the tree's volume has, by name."""
    if hasattr(volume, "extract_mesh_on_device"):
        return {"scikit-image, host": volume.extract_mesh_on_host, "own, device": volume.extract_mesh_on_device}
    return {"scikit-image, host": volume.extract_mesh}


def speed(frames: int, rounds: int, device: str) -> dict:
    """Integration (ms a frame) of each integration the tree has, and mesh extraction (s) of each extraction."""
    from endoflow.config import Params
    from endoflow.reconstruction.fusion import TSDFVolume

    K, rendered = rendered_frames(frames, 480)
    voxel = Params().model.max_depth / 4 / K[0, 0]  # reconstruct's default until it followed the depth
    if device != "cpu":
        kinds = {"tensor code": {"device": device}}
    elif "compiled" in inspect.signature(TSDFVolume).parameters:
        kinds = {"compiled loops": {"compiled": True}, "tensor code": {"compiled": False}}
    else:
        kinds = {"tensor code": {}}
    fused(K, rendered[:2], voxel, 4 * voxel, **next(iter(kinds.values())))  # compiles or warms up, untimed
    times: dict[str, list[float]] = {kind: [] for kind in kinds}
    volumes = {}
    for _ in range(rounds):
        for kind, options in kinds.items():  # alternating, so that load from other processes hits both alike
            start = time.perf_counter()
            volumes[kind] = fused(K, rendered, voxel, 4 * voxel, **options)
            synchronize(device)
            times[kind].append((time.perf_counter() - start) / len(rendered) * 1e3)
    result = {"voxel_cm": voxel, "blocks": next(iter(volumes.values())).block_count, "device": device,
              "integrate_ms": {kind: statistics.median(values) for kind, values in times.items()}}
    if len(volumes) == 2:
        first, second = volumes.values()
        result["identical"] = all(torch.equal(getattr(first, name), getattr(second, name))
                                  for name in ("_keys", "_rows", "_tsdf", "_weight", "_colour"))
    volume = next(iter(volumes.values()))
    result["extract_s"], result["vertices"] = {}, {}
    for _ in range(rounds):
        for name, extract in extractions(volume).items():
            start = time.perf_counter()
            mesh = extract()
            seconds = time.perf_counter() - start  # the mesh is on the host: nothing left to wait for
            result["extract_s"][name] = min(seconds, result["extract_s"].get(name, seconds))
            result["vertices"][name] = len(mesh.vertices)
    return result


def synchronize(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def floor(frames: int) -> list[dict]:
    """The floor's vertices against the ground truth at each truncation."""
    from endoflow.reconstruction.measure import SurfacePoints, capped_distances, surface_errors

    K, rendered = rendered_frames(frames, 64)
    truth = SurfacePoints(FLOOR_VOXEL_CM / 2)  # the ground-truth sampling of the reconstruct stage
    for depth, _, T_world_cam in rendered:
        truth.add(depth, K, T_world_cam)
    rows = []
    for voxels in TRUNCATIONS:
        volume = fused(K, rendered, FLOOR_VOXEL_CM, voxels * FLOOR_VOXEL_CM)
        for name, extract in extractions(volume).items():
            vertices = extract().vertices
            off = capped_distances(truth.points(), vertices)
            rows.append({"truncation": voxels, "extraction": name, "vertices": len(vertices),
                         "percentiles": [float(np.percentile(off, q)) for q in (50, 75, 90)],
                         "beyond_2_voxels": float(np.mean(off > 2 * FLOOR_VOXEL_CM)),
                         "complete": surface_errors(vertices, truth.points(), FLOOR_VOXEL_CM)["completeness_ratio"]})
    return rows


def measure(frames: int, rounds: int, threads: int, device: str) -> dict:
    torch.set_num_threads(threads)
    return {"speed": speed(frames, rounds, device), "floor": floor(frames)}


def in_child(tree: Path, args: argparse.Namespace) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "result.json"
        subprocess.run([sys.executable, __file__, "--worker", str(out), "--frames", str(args.frames),
                        "--rounds", str(args.rounds), "--threads", str(args.threads), "--device", args.device],
                       env=environment_importing(tree), cwd=ROOT, check=True)
        return json.loads(out.read_text())


def report(name: str, result: dict) -> None:
    speed_ = result["speed"]
    print(f"\n{name}: 480 px, voxel {speed_['voxel_cm']:.4f} cm, {speed_['blocks']} blocks, {speed_['device']}")
    for kind, ms in speed_["integrate_ms"].items():
        print(f"  integrate, {kind}: {ms:.1f} ms a frame")
    if "identical" in speed_:
        print(f"  the two volumes {'are identical' if speed_['identical'] else 'DIFFER'}")
    for kind, seconds in speed_["extract_s"].items():
        print(f"  mesh extraction, {kind}: {seconds:.2f} s (best of the rounds), {speed_['vertices'][kind]} vertices")
    print(f"  floor at 64 px, voxel {FLOOR_VOXEL_CM} cm, on the CPU: truncation | extraction | vertices | vertex to "
          f"ground truth, median / 75th / 90th (cm) | vertices beyond 2 voxels | ground truth within 2 voxels")
    for row in result["floor"]:
        median, upper, tail = row["percentiles"]
        print(f"  {row['truncation']} voxels | {row['extraction']} | {row['vertices']} | {median:.3f} / {upper:.3f} / "
              f"{tail:.3f} | {100 * row['beyond_2_voxels']:.1f} % | {100 * row['complete']:.1f} %")


def main() -> None:
    args = parse_args()
    if args.worker is not None:
        sys.path.append(str(ROOT))  # tests.small_model; the endoflow on PYTHONPATH comes first
        args.worker.write_text(json.dumps(measure(args.frames, args.rounds, args.threads, args.device)))
        return
    results = {}
    if args.baseline is not None:
        results[f"before ({args.baseline})"] = in_child(args.baseline, args)
    results["after (this tree)"] = in_child(ROOT, args)
    print(f"\nTSDF fusion, {args.frames} frames, {args.threads} torch threads, median of {args.rounds} rounds (mesh "
          f"extraction: best of them)")
    for name, result in results.items():
        report(name, result)
    if len(results) == 2:
        before, after = (result["speed"] for result in results.values())
        host = before["extract_s"]["scikit-image, host"]
        print("\ntime over before's (below 1: faster): mesh extraction, "
              + ", ".join(f"{kind} {seconds / host:.2f}" for kind, seconds in after["extract_s"].items())
              + "; integration, " + ", ".join(f"{kind} {ms / before['integrate_ms']['tensor code']:.2f}"
                                               for kind, ms in after["integrate_ms"].items()))


if __name__ == "__main__":
    main()
