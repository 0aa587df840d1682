"""ONNX export of the trained model's two networks, verified against torch with onnxruntime.

Two graphs, each a plain function of float32 tensors with a dynamic batch dimension (dim 0):

- ``depth_net.onnx``: ``rgb [B, 3, H, W]`` (RGB in [0, 1]) -> ``depth_cm [B, 1, H, W]``, z-depth in cm within
  ``[model.min_depth, model.max_depth]``: :meth:`EndoflowModel.predict_depth`, disparity -> depth included.
- ``pose_net.onnx``: ``target, source [B, 3, H, W]`` -> ``T_source_target [B, 4, 4]``:
  :meth:`EndoflowModel.predict_pose` with ``source_is_next=True``, the mean (no sampling). It maps points of
  the target (earlier) camera frame into the source (next) one, OpenCV camera, translation in cm.

H and W are fixed to the training size (``data.size``, square): the graphs are traced at that size.
``export.json`` (written after both graphs; it holds their SHA-256s) records the inputs, outputs, units,
conventions, opset, the model file's SHA-256 and the measured torch-vs-onnxruntime differences.

Exporter: ``torch.onnx.export(dynamo=True)`` (torch.export + onnxscript). The TorchScript exporter
(``dynamo=False``) cannot export this model: the latent bank's blur builds its depthwise kernel from the
traced channel count, which that exporter's shape inference loses after the edge padding, and it refuses a
"convolution for kernel of unknown shape". torch.export keeps every dimension static except the declared
batch dimension.
"""

from __future__ import annotations

import logging
import warnings
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np
import onnxruntime
import torch
from torch import nn

from endoflow.io import atomic_path, file_sha256, write_json
from endoflow.models.endoflow_model import load_trained_model
from endoflow.models.model_file import ModelRecord
from endoflow.progress import logger_quieted

# torchlib (the dynamo exporter's op library) is written for opset 18: asking for it means no version
# conversion pass, and onnxruntime supports it from 1.14 on.
OPSET = 18
DEPTH_FILE, POSE_FILE, REPORT_FILE = "depth_net.onnx", "pose_net.onnx", "export.json"
VERIFY_BATCH, VERIFY_SEED = 2, 0

# Tolerances, relative to the largest magnitude of the torch output taken as at least 1 (a pose's rotation
# entries are of unit scale whatever its translation). Both runtimes compute in float32 (eps 1.2e-7) but sum
# the convolutions in other orders; over ~40 layers that leaves ~1e-5 absolute error on the disparity logits.
# Disparity -> depth amplifies it: depth = 1 / (a + b * sigmoid(logit)) changes by at most
# (max_depth / min_depth) / 4 (50 at the defaults) times the logit error, relatively, at depth = max_depth:
# ~5e-4. DEPTH_RTOL = 1e-3 of the largest depth passes that float32 noise and still fails a real export
# error (a wrong padding mode or a dropped normalisation changes depth by percent). The pose vector is 0.01
# times a spatial mean of the head, so its float32 noise is orders smaller; 1e-4 of the matrix scale is ample.
DEPTH_RTOL = 1e-3
POSE_RTOL = 1e-4


class ExportVerificationError(RuntimeError):
    """The exported graph does not load in onnxruntime or does not reproduce torch within the tolerance."""


@dataclass
class GraphReport:
    """One exported graph: its file, size in bytes, SHA-256, and torch vs onnxruntime difference."""

    name: str
    file: str
    bytes: int
    sha256: str
    max_abs_diff: float
    tolerance: float
    inputs: list[dict[str, Any]]
    outputs: list[dict[str, Any]]


@dataclass
class ExportReport:
    """What :func:`export_onnx` wrote to ``out_dir`` and measured; ``model`` names the model file (or MLflow URI);
    ``record`` is the content of ``export.json``."""

    out_dir: Path
    model: str
    model_sha256: str
    image_size: tuple[int, int]
    graphs: list[GraphReport]
    record: dict[str, Any]


class DepthGraph(nn.Module):
    """What ``depth_net.onnx`` computes: ``rgb [B, 3, H, W]`` in [0, 1] -> z-depth ``[B, 1, H, W]`` in cm."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.model.predict_depth(rgb)


class PoseGraph(nn.Module):
    """What ``pose_net.onnx`` computes: the mean ``T_source_target [B, 4, 4]`` (cm) of a frame and the next."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, target: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        return self.model.predict_pose(target, source, source_is_next=True)


def export_onnx(model_path: str | Path, out_dir: str | Path, model_label: Optional[str] = None) -> ExportReport:
    """Export the model file's DepthNet and PoseNet (mean head) to ONNX in ``out_dir`` and verify them;
    ``model_label`` names the model in ``export.json`` (default: ``model_path``; an MLflow URI for a model
    downloaded to a temporary file).

    Each graph is written to a temporary beside its target, checked with onnxruntime (CPU) against torch on
    a seeded batch of :data:`VERIFY_BATCH` random images, and renamed into place only when both graphs pass;
    ``export.json`` follows. Other files in ``out_dir`` are left alone.

    Raises:
        FileNotFoundError, DataFormatError: from loading the model file (they name it).
        ExportVerificationError: a graph that onnxruntime cannot run or that differs from torch by more than
            its tolerance (nothing is replaced then).
    """
    model_path, out_dir = Path(model_path), Path(out_dir)
    model, record = load_trained_model(model_path, torch.device("cpu"))
    size = record.params.data.size
    shape = (VERIFY_BATCH, 3, size, size)
    generator = torch.Generator().manual_seed(VERIFY_SEED)
    rgb, target, source = (torch.rand(shape, generator=generator) for _ in range(3))
    specs = [
        (DEPTH_FILE, DepthGraph(model).eval(), {"rgb": rgb}, "depth_cm", DEPTH_RTOL),
        (POSE_FILE, PoseGraph(model).eval(), {"target": target, "source": source}, "T_source_target", POSE_RTOL),
    ]
    interfaces = graph_interfaces(record)
    graphs: list[GraphReport] = []
    with ExitStack() as commits:  # the renames happen when the block ends, after every graph has passed
        for file, graph, inputs, output, rtol in specs:
            temporary = commits.enter_context(atomic_path(out_dir / file))
            export_graph(graph, inputs, output, temporary)
            with torch.no_grad():
                expected = graph(*inputs.values()).numpy()
            diff = verify_graph(temporary, {k: v.numpy() for k, v in inputs.items()}, expected, rtol,
                                 name=str(out_dir / file))
            name = Path(file).stem
            graphs.append(GraphReport(name=name, file=file, bytes=temporary.stat().st_size,
                                      sha256=file_sha256(temporary), max_abs_diff=diff,
                                      tolerance=rtol * output_scale(expected), inputs=interfaces[name][0],
                                      outputs=interfaces[name][1]))
    report = _report(model_path, model_label or str(model_path), out_dir, record, graphs)
    write_json(out_dir / REPORT_FILE, report.record)
    return report


def export_graph(graph: nn.Module, inputs: dict[str, torch.Tensor], output: str, path: Path) -> None:
    """Write ``graph`` traced on ``inputs`` to the single file ``path`` (weights inside), batch dim dynamic."""
    batch = torch.export.Dim("batch")  # one symbol: the pose graph's two inputs share their batch size
    with _quiet_exporter():
        program = torch.onnx.export(
            graph, tuple(inputs.values()), dynamo=True, opset_version=OPSET, input_names=list(inputs),
            output_names=[output], dynamic_shapes={name: {0: batch} for name in inputs}, verbose=False,
        )
    # One self-contained file (below protobuf's 2 GB limit), so a single rename publishes it.
    program.save(path, external_data=False)


@contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporter's notes that say nothing about this model: torchvision ops it skips registering
    (logged), a deprecation inside torch, and that the pose inputs' shared batch symbol is named once."""
    with logger_quieted("torch.onnx._internal.exporter._registration", logging.ERROR), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*LeafSpec.*is deprecated", category=FutureWarning)
        warnings.filterwarnings("ignore", message=".*axis name: batch will not be used", category=UserWarning)
        yield


def verify_graph(path: Path, inputs: dict[str, np.ndarray], expected: np.ndarray, rtol: float,
                 name: str | None = None) -> float:
    """Run the ONNX file ``path`` with onnxruntime (CPU) on ``inputs``; its max abs difference to ``expected``.

    Raises:
        ExportVerificationError: naming ``name`` (default: ``path``): the graph does not load or run, or it
            differs by more than ``rtol`` times the output's scale (see :func:`output_scale`).
    """
    label = name or str(path)
    try:
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        (got,) = session.run(None, inputs)
    except Exception as exc:  # onnxruntime raises its own (pybind) exception types
        raise ExportVerificationError(f"{label}: onnxruntime could not run the exported graph "
                                      f"({str(exc).splitlines()[0][:300]})") from None
    if got.shape != expected.shape:
        raise ExportVerificationError(f"{label}: onnxruntime output shape {got.shape}, torch {expected.shape}")
    diff = float(np.max(np.abs(got.astype(np.float64) - expected)))
    tolerance = rtol * output_scale(expected)
    if not diff <= tolerance:  # also catches NaN
        raise ExportVerificationError(f"{label}: onnxruntime differs from torch by {diff:.3g} (max abs), "
                                      f"more than the tolerance {tolerance:.3g}")
    return diff


def output_scale(expected: np.ndarray) -> float:
    """The magnitude tolerances are relative to: the largest absolute output value, taken as at least 1 (a
    pose's rotation entries are of unit scale whatever its translation)."""
    return max(1.0, float(np.max(np.abs(expected))))


def graph_interfaces(record: ModelRecord) -> dict[str, tuple[list[dict[str, Any]], list[dict[str, Any]]]]:
    """Each graph's (inputs, outputs) as ``export.json`` documents them: names, shapes, units, conventions."""
    size, cfg = record.params.data.size, record.params.model
    image = {"dtype": "float32", "shape": ["batch", 3, size, size], "range": [0.0, 1.0],
             "meaning": "RGB (channel order R, G, B) in [0, 1] at the training size"}
    depth = {"name": "depth_cm", "dtype": "float32", "shape": ["batch", 1, size, size], "unit": "cm",
             "range": [cfg.min_depth, cfg.max_depth],
             "meaning": "z-depth along the optical axis (EndoflowModel.predict_depth)"}
    pose = {"name": "T_source_target", "dtype": "float32", "shape": ["batch", 4, 4],
            "unit": "cm (translation; the rotation block is orthonormal)",
            "meaning": "mean rigid transform mapping points of the target camera frame into the source (next) "
                       "camera frame (EndoflowModel.predict_pose, source_is_next=True)"}
    return {
        "depth_net": ([{"name": "rgb", **image}], [depth]),
        "pose_net": ([{"name": "target", **image, "meaning": "the earlier frame: " + image["meaning"]},
                      {"name": "source", **image, "meaning": "the next frame: " + image["meaning"]}], [pose]),
    }


def _report(model_path: Path, model_label: str, out_dir: Path, record: ModelRecord,
            graphs: list[GraphReport]) -> ExportReport:
    """The export's record (``export.json``): the graphs' interfaces, conventions, and what was measured."""
    size = record.params.data.size
    model_sha256 = file_sha256(model_path)
    data = {
        "format": "onnx",
        "opset": OPSET,
        "exporter": f"torch.onnx.export(dynamo=True), torch {torch.__version__}",
        "model": {"path": model_label, "sha256": model_sha256, "epoch": record.epoch,
                  "mlflow_run_id": record.mlflow_run_id},
        "image_size": [size, size],
        "conventions": {
            "camera": "OpenCV: x right, y down, z forward; right-handed",
            "pose": "T_a_b maps points from frame b into frame a: p_a = T_a_b @ p_b; translation in cm",
            "depth": "z-depth in cm",
            "batch": "dimension 0 of every input and output is dynamic",
        },
        "verification": {"runtime": f"onnxruntime {onnxruntime.__version__}, CPUExecutionProvider",
                         "batch": VERIFY_BATCH, "seed": VERIFY_SEED, "inputs": "uniform random images in [0, 1]",
                         "tolerance": "rtol times max(1, largest |torch output|)",
                         "rtol": {"depth_net": DEPTH_RTOL, "pose_net": POSE_RTOL}},
        "graphs": {g.name: {"file": g.file, "bytes": g.bytes, "sha256": g.sha256, "inputs": g.inputs,
                            "outputs": g.outputs, "max_abs_diff": g.max_abs_diff, "tolerance": g.tolerance}
                   for g in graphs},
    }
    return ExportReport(out_dir=out_dir, model=model_label, model_sha256=model_sha256,
                        image_size=(size, size), graphs=graphs, record=data)


def format_export(report: ExportReport) -> str:
    """A short summary for the command line: files, sizes, max abs differences."""
    lines = [f"exported {report.model} (sha256 {report.model_sha256[:12]}, images "
             f"{report.image_size[0]}x{report.image_size[1]}) to {report.out_dir}, opset {OPSET}:"]
    for g in report.graphs:
        unit = "cm" if g.name == "depth_net" else "(4x4 entries; translation in cm)"
        lines.append(f"  {g.file:<16} {g.bytes / 2**20:8.1f} MiB  max |onnxruntime - torch| = "
                     f"{g.max_abs_diff:.3g} {unit} (tolerance {g.tolerance:.3g})")
    lines.append(f"  {REPORT_FILE:<16} inputs, outputs, units, conventions")
    return "\n".join(lines)
