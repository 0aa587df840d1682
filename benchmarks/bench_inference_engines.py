"""The two networks on the CPU: torch (as ``reconstruct`` runs them) against onnxruntime (the graphs
``endoflow model export`` writes), in the same run.

    python benchmarks/bench_inference_engines.py [--model FILE | --preset presets/paper.yaml] [--threads 2]
        [--batch 1] [--rounds 5]

Without ``--model`` the networks are the preset's (default: ``params.yaml``) with random weights and a random
bank: the time of a forward pass does not depend on the weights. torch runs in float32 with the layout
``reconstruct`` gives the weights and frames (:func:`endoflow.devices.to_compute_layout`), under
``torch.no_grad``; onnxruntime runs the exported graphs with ``--threads`` intra-op threads. Rounds alternate
between the two engines, so load from other processes hits both alike; each round times one call after a
warm-up call, and the medians are reported with their ratio (torch's time over onnxruntime's: above 1 means
onnxruntime is faster) and the largest difference between the two outputs. The export's own time is printed
too: it is paid once per model.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import onnxruntime
import torch

from endoflow.config import load_params
from endoflow.devices import images_to_device, to_compute_layout
from endoflow.models.endoflow_model import EndoflowModel, build_model, load_trained_model
from endoflow.models.export import DepthGraph, PoseGraph, export_graph

PROJECT = Path(__file__).resolve().parents[1]


def networks(args: argparse.Namespace) -> tuple[EndoflowModel, int, str]:
    """The model in eval mode, its input size, and what it is (for the report)."""
    if args.model:
        model, record = load_trained_model(args.model, torch.device("cpu"))
        return model, record.params.data.size, str(args.model)
    params = load_params(args.preset)
    torch.manual_seed(0)
    return build_model(params, None).eval(), params.data.size, f"{args.preset}, random weights"


def onnx_session(path: Path, threads: int) -> onnxruntime.InferenceSession:
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def seconds_of(call: Callable[[], object]) -> float:
    call()  # warm-up: first-call allocations and, for onnxruntime, its arena
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def compare(name: str, torch_call: Callable[[], np.ndarray], onnx_call: Callable[[], np.ndarray], rounds: int,
            batch: int) -> None:
    times: dict[str, list[float]] = {"torch": [], "onnxruntime": []}
    for _ in range(rounds):
        times["torch"].append(seconds_of(torch_call))
        times["onnxruntime"].append(seconds_of(onnx_call))
    difference = float(np.abs(torch_call() - onnx_call()).max())
    medians = {engine: statistics.median(values) * 1e3 / batch for engine, values in times.items()}
    print(f"{name}: torch {medians['torch']:.1f} ms a frame, onnxruntime {medians['onnxruntime']:.1f} "
          f"({medians['torch'] / medians['onnxruntime']:.2f}x); largest difference {difference:.2e}; rounds, ms a "
          f"frame: torch {', '.join(f'{t * 1e3 / batch:.0f}' for t in times['torch'])}; onnxruntime "
          f"{', '.join(f'{t * 1e3 / batch:.0f}' for t in times['onnxruntime'])}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, default=None, help="a model file (default: random weights)")
    parser.add_argument("--preset", type=Path, default=PROJECT / "params.yaml",
                        help="params of the random-weight networks (without --model)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=1, help="frames per call")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    model, size, label = networks(args)
    cpu = torch.device("cpu")
    generator = torch.Generator().manual_seed(0)
    frames = [(torch.rand(args.batch, 3, size, size, generator=generator) * 255).to(torch.uint8) for _ in range(2)]
    rgb, source = (images_to_device(f, cpu, "float32").contiguous() for f in frames)
    print(f"{label}: {size} px, batch {args.batch}, {args.threads} threads, torch {torch.__version__}, "
          f"onnxruntime {onnxruntime.__version__}", flush=True)

    with tempfile.TemporaryDirectory(prefix="endoflow-bench-onnx-") as folder:
        depth_file, pose_file = Path(folder) / "depth_net.onnx", Path(folder) / "pose_net.onnx"
        start = time.perf_counter()
        export_graph(DepthGraph(model).eval(), {"rgb": rgb}, "depth_cm", depth_file)
        export_graph(PoseGraph(model).eval(), {"target": rgb, "source": source}, "T_source_target", pose_file)
        print(f"export of both graphs: {time.perf_counter() - start:.1f} s", flush=True)
        depth_session, pose_session = onnx_session(depth_file, args.threads), onnx_session(pose_file, args.threads)

        laid_out = to_compute_layout(model, cpu, "float32", size)
        rgb_in, source_in = (images_to_device(f, cpu, "float32") for f in frames)  # reconstruct's layout

        @torch.no_grad()
        def torch_depth() -> np.ndarray:
            return laid_out.predict_depth(rgb_in).numpy()

        @torch.no_grad()
        def torch_pose() -> np.ndarray:
            return laid_out.predict_pose(rgb_in, source_in, source_is_next=True).numpy()

        compare("depth network", torch_depth, lambda: depth_session.run(None, {"rgb": rgb.numpy()})[0],
                args.rounds, args.batch)
        compare("pose network", torch_pose,
                lambda: pose_session.run(None, {"target": rgb.numpy(), "source": source.numpy()})[0],
                args.rounds, args.batch)


if __name__ == "__main__":
    main()
