"""The trained model as an MLflow model: logged with every training run, registered on request, and read back
from a ``models:/<name>/<version>`` (or ``runs:/<run id>/model``) URI.

The logged model is a pyfunc defined by code (``mlflow_pyfunc_entry.py``, MLflow's "models from code"), with
the model file as its one artifact and this package as its code, so ``mlflow.pyfunc.load_model`` works on any
machine with the dependencies: it takes consecutive RGB frames of one video and returns their depth and camera
path (see :class:`EndoflowPyfunc`). Nothing is pickled: the weights load with ``weights_only=True``.

endoflow itself never runs a logged model's code: :func:`local_model_file` downloads the logged model and hands
back its model file, which is read as every model file is (:func:`endoflow.models.model_file.load_model_file`).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import tempfile
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np
import yaml

from endoflow.errors import DataFormatError
from endoflow.models.model_file import load_model_file
from endoflow.progress import environment_default, logger_quieted

MODEL_URI_SCHEMES = ("models:/", "runs:/")
ARTIFACT_NAME = "model"  # where the logged model sits among its run's artifacts
MODEL_FILE_ARTIFACT = "model_file"  # the pyfunc's artifact key for the model file
ENTRY_FILE = Path(__file__).with_name("mlflow_pyfunc_entry.py")
PACKAGE_FOLDER = Path(__file__).resolve().parents[1]
# what loading and running the pyfunc imports, pinned to the versions it was logged with
REQUIREMENTS = ("torch", "numpy", "kornia", "pyyaml", "mlflow")
EXAMPLE_FRAMES = 2
PROGRESS_BAR_ENV = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


def is_model_uri(location: str | Path) -> bool:
    """Whether ``location`` names an MLflow model rather than a file."""
    return str(location).startswith(MODEL_URI_SCHEMES)


class EndoflowPyfunc:
    """``predict(frames)``: ``frames`` uint8 RGB ``[N, S, S, 3]``, consecutive frames of one video at the
    model's input size ``S`` (``data.size``); returns ``depth_cm`` float32 ``[N, S, S]`` (z-depth) and
    ``T_world_cam`` float64 ``[N, 4, 4]``, camera-to-world poses chained from the first frame (the identity),
    OpenCV camera, in the model's scale (cm on the data it was trained on). ``mlflow_pyfunc_entry.py`` adds
    MLflow's ``PythonModel`` as a base, so that importing this module does not import MLflow."""

    def load_context(self, context: Any) -> None:
        import torch

        from endoflow.devices import to_compute_layout
        from endoflow.models.endoflow_model import load_trained_model

        self.device = torch.device("cpu")
        model, record = load_trained_model(context.artifacts[MODEL_FILE_ARTIFACT], self.device)
        self.model = to_compute_layout(model, self.device, "float32", record.params.data.size)

    def predict(self, context: Any, model_input: np.ndarray, params: Optional[dict] = None) -> dict[str, np.ndarray]:
        import torch

        from endoflow.devices import images_to_device
        from endoflow.geometry.pose import chain_step

        frames = np.asarray(model_input)
        images = images_to_device(torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous(), self.device,
                                  "float32")
        with torch.no_grad():
            depth = self.model.predict_depth(images)[:, 0].float().numpy()
            steps = (self.model.predict_pose(images[:-1], images[1:]).double().numpy() if len(images) > 1
                     else np.zeros((0, 4, 4)))
        poses = [np.eye(4)]
        for T_cur_prev in steps:
            poses.append(chain_step(poses[-1], T_cur_prev))
        return {"depth_cm": depth, "T_world_cam": np.stack(poses)}


def model_signature(size: int) -> Any:
    """Inputs and outputs of :class:`EndoflowPyfunc` at input size ``size``, as MLflow records them."""
    from mlflow.models import ModelSignature
    from mlflow.types import Schema, TensorSpec

    return ModelSignature(
        inputs=Schema([TensorSpec(np.dtype(np.uint8), (-1, size, size, 3))]),
        outputs=Schema([TensorSpec(np.dtype(np.float32), (-1, size, size), "depth_cm"),
                        TensorSpec(np.dtype(np.float64), (-1, 4, 4), "T_world_cam")]),
    )


def example_frames(size: int) -> np.ndarray:
    """Two frames of a smooth colour ramp, the second shifted by a pixel: a small, deterministic input
    example."""
    ramp = np.linspace(0, 255, size, dtype=np.float64)
    frame = np.stack([np.add.outer(ramp, ramp) / 2, np.add.outer(ramp, ramp[::-1]) / 2,
                      np.full((size, size), 128.0)], axis=-1).astype(np.uint8)
    return np.stack([frame, np.roll(frame, 1, axis=1)])[:EXAMPLE_FRAMES]


def requirements() -> list[str]:
    """:data:`REQUIREMENTS` pinned to this environment's versions (without a local tag such as ``+cpu``, which
    no package index serves)."""
    return [f"{name}=={importlib.metadata.version(name).split('+')[0]}" for name in REQUIREMENTS]


def log_mlflow_model(tracking_uri: str, run_id: str, model_path: Path, registered_name: Optional[str]) -> str:
    """Log the model file as an MLflow model under the run's ``model/`` artifacts (registered as a new version
    of ``registered_name`` when given); returns its ``models:/`` URI."""
    import mlflow

    size = load_model_file(model_path).params.data.size
    # MLflow notes at INFO that it checks the input example against the signature: it raises if they disagree
    with using_store(tracking_uri), logger_quieted("mlflow.pyfunc"), mlflow.start_run(run_id=run_id):
        info = mlflow.pyfunc.log_model(
            name=ARTIFACT_NAME, python_model=str(ENTRY_FILE), artifacts={MODEL_FILE_ARTIFACT: str(model_path)},
            code_paths=[str(PACKAGE_FOLDER)], signature=model_signature(size), input_example=example_frames(size),
            pip_requirements=requirements(), registered_model_name=registered_name)
    return info.model_uri


@contextlib.contextmanager
def using_store(uri: str) -> Iterator[None]:
    """Within: MLflow's fluent API (``log_model``, ``models:/`` downloads) uses the store at ``uri`` for runs and
    registered models, and draws no download progress bars unless the environment asks for them; the
    process-wide URIs are restored after, so that nothing else is redirected."""
    import mlflow

    previous = mlflow.get_tracking_uri(), mlflow.get_registry_uri()
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    try:
        # log_model downloads the model it has just logged to check the input example, and MLflow drew a progress
        # bar for it in every training stage's log: library noise
        with environment_default(PROGRESS_BAR_ENV, "false"):
            yield
    finally:
        mlflow.set_tracking_uri(previous[0])
        mlflow.set_registry_uri(previous[1])


@contextlib.contextmanager
def local_model_file(location: str | Path, tracking_uri: str) -> Iterator[Path]:
    """The model file at ``location``: the path itself, or for an MLflow model URI the model file of the
    logged model, downloaded into a temporary folder for the duration (only files are read, nothing runs)."""
    if not is_model_uri(location):
        yield Path(location)
        return
    import mlflow
    from mlflow.exceptions import MlflowException

    with tempfile.TemporaryDirectory(prefix="endoflow-model-") as folder, using_store(tracking_uri):
        try:
            local = Path(mlflow.artifacts.download_artifacts(artifact_uri=str(location), dst_path=folder,
                                                             tracking_uri=tracking_uri))
        except MlflowException as exc:
            raise FileNotFoundError(f"{location}: no such model in {tracking_uri} ({exc.message})") from exc
        yield model_file_of(local, str(location))


def model_file_of(model_dir: Path, location: str) -> Path:
    """The model file of a downloaded MLflow model, named by its ``MLmodel`` (plain YAML); a path leading out of
    ``model_dir`` (``../``, absolute, a link) is refused before anything is read there."""
    description = model_dir / "MLmodel"
    if not description.is_file():
        raise FileNotFoundError(f"{location}: not an MLflow model (no MLmodel file)")
    flavour = (yaml.safe_load(description.read_text()).get("flavors") or {}).get("python_function") or {}
    entry = (flavour.get("artifacts") or {}).get(MODEL_FILE_ARTIFACT) or {}
    if "path" not in entry:
        raise FileNotFoundError(f"{location}: not an endoflow model (its MLmodel names no {MODEL_FILE_ARTIFACT} "
                                f"artifact)")
    artifact = model_dir / str(entry["path"])
    if model_dir.resolve() not in artifact.resolve().parents:
        raise DataFormatError(location, f"its MLmodel names the model file {entry['path']!r}, outside the downloaded "
                                        f"model: refused (the logged model has been tampered with)")
    return artifact
