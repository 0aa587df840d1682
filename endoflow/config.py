"""Typed configuration: ``params.yaml`` validated once into dataclasses.

Every stage and command reads its settings through :func:`load_params`. Unknown keys and values of the
wrong type fail with :class:`ConfigError` naming the dotted key (``model.latent_bank``), so a typo in
``params.yaml`` or ``dvc exp run -S`` never passes silently. Keys left out take the defaults below.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional, Sequence, Union

import yaml


class ConfigError(ValueError):
    """A parameter is unknown, missing or of the wrong type; the message names the key."""


# --------------------------------------------------------------------------------------------- data
@dataclass
class SimColConfig:
    root: str = "data/raw/synthetic/SimCol3D"
    # 3x3 pixel K at `reference_size`, overriding cam.txt (row-major nested lists); null reads cam.txt.
    intrinsics: Optional[list[list[float]]] = None
    # cam.txt describes images of this width; K is scaled by (stored width / reference_size).
    reference_size: int = 475
    val: list[str] = field(default_factory=lambda: ["S4", "S9", "S14", "B4", "B9", "B14"])
    test: list[str] = field(
        default_factory=lambda: ["S5", "S10", "S15", "B5", "B10", "B15", "O1", "O2", "O3"]
    )


@dataclass
class EndoSLAMConfig:
    root: str = "data/raw/synthetic/EndoSLAM"
    # unitycam: synthetic VR-Caps export; camera: real HighCam/LowCam/... recordings; auto: detect.
    layout: Literal["auto", "unitycam", "camera"] = "auto"
    # Pose translation units to cm (UnityCam units are unconfirmed; real-camera sheets claim metres).
    unitycam_translation_to_cm: float = 1.0
    camera_translation_to_cm: float = 100.0
    # UnityCam depth PNGs hold relative distance 0..255; this is the distance that 255 stands for.
    depth_full_scale_cm: float = 20.0
    depth_is_ray_length: bool = False
    fps: float = 30.0
    # 3x3 pixel K for the stored frames; null uses the documented third-party UnityCam K (scaled).
    intrinsics: Optional[list[list[float]]] = None
    # Real-camera poses: convert from a left-handed frame like UnityCam's?
    camera_poses_left_handed: bool = False
    split: Literal["train", "val", "test"] = "test"


@dataclass
class SceneNetConfig:
    root: str = "data/raw/synthetic/SceneNet"
    max_frames_per_trajectory: Optional[int] = None


@dataclass
class DataConfig:
    size: int = 128  # stored square size of shard images (centre crop to square, then resize)
    simcol: SimColConfig = field(default_factory=SimColConfig)
    endoslam: EndoSLAMConfig = field(default_factory=EndoSLAMConfig)
    scenenet: SceneNetConfig = field(default_factory=SceneNetConfig)


# -------------------------------------------------------------------------------------------- synth
@dataclass
class SynthLayoutConfig:
    sequences: int
    frames: int


@dataclass
class SynthConfig:
    out: str = "data/raw/synthetic"
    size: int = 128
    seed: int = 0
    workers: int = 2  # processes rendering sequences in parallel (CPU)
    device: str = "cpu"  # torch device for rendering, e.g. "cuda" (then one process)
    simcol: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(15, 60))
    endoslam: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(2, 120))
    scenenet: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(60, 20))


# ---------------------------------------------------------------------------------------- preprocess
@dataclass
class PreprocessConfig:
    out: str = "data/shards"
    workers: int = 2
    samples_per_shard: int = 128
    # Each split's shard count is a multiple of this, so whole shards divide evenly over workers.
    shard_multiple: int = 4
    neighbour_offset: int = 1  # prev/next are frames cur -/+ this offset


# ------------------------------------------------------------------------------------ latent bank
@dataclass
class LatentBankConfig:
    """Generative pretraining of the StyleGAN-like depth generator (WGAN-GP, progressive growing)."""

    shards: str = "data/shards/scenenet"
    out: str = "models/latent_bank.pt"
    resolution: int = 64  # final generator resolution (power of two)
    # First generator block; with resolution 64 the bank has 5 blocks, one per DepthNet encoder level.
    start_resolution: int = 4
    latent_dim: int = 128
    style_dim: int = 128
    mapping_layers: int = 4
    channel_base: int = 512
    channel_max: int = 128
    batch_size: int = 16
    # Generator steps at each resolution: one number for all, or a list from start_resolution up.
    steps_per_stage: Union[int, list[int]] = 300
    lr: float = 1e-4  # fixed, as the paper
    betas: list[float] = field(default_factory=lambda: [0.0, 0.99])
    # Critic steps per generator step: one number for all resolutions, or a list like steps_per_stage.
    n_critic: Union[int, list[int]] = 1
    gp_gamma: float = 10.0
    ema_decay: float = 0.999
    # Initial scale of the synthesis convolutions relative to PyTorch's default; they are scale-free (AdaIN
    # follows), so below 1 they learn faster at the fixed lr (see latent_bank.shrink_scale_free_weights).
    conv_init_scale: float = 0.25
    swd_samples: int = 256
    drift_weight: float = 0.001  # ProGAN's penalty on squared real scores, keeps critic outputs bounded
    fade_fraction: float = 0.5  # share of each new stage spent fading the new resolution in
    # Maps are centred log-depth divided by this (natural-log units), clipped to [-1, 1].
    depth_log_range: float = 1.5
    holdout_fraction: float = 0.1  # held out of train for the SWD when the shards have no val split


# ------------------------------------------------------------------------------------------ model
@dataclass
class ModelConfig:
    latent_bank: bool = True  # ablation: false gives the same DepthNet without the bank
    pose_vae: bool = True  # ablation: false gives a deterministic PoseNet
    min_depth: float = 0.1  # cm
    max_depth: float = 20.0  # cm
    encoder_weights: Optional[str] = None  # optional local ResNet-18 ImageNet state dict
    scales: int = 4
    # The frozen bank injects its learned per-pixel noise while training (never at evaluation).
    bank_noise: bool = False
    # Initial log-variance of the pose VAE (std exp(-4.5) ~ 0.011 rad / cm): small, so early samples
    # do not swamp the warp; the KL term then pulls it up against the reprojection loss.
    pose_logvar_init: float = -9.0


@dataclass
class LossConfig:
    photometric: Literal["mse", "ssim_l1"] = "ssim_l1"
    ssim_weight: float = 0.85
    min_reprojection: bool = True
    automask: bool = True
    smoothness_weight: float = 1e-3
    multiscale: bool = True
    # beta. The paper gives no value; 1e-3 pushed the pose log-variance up until sampling noise (~0.03 rad)
    # swamped the per-frame rotation of the default data, and pose learned nothing (docs/method.md).
    kl_weight: float = 1e-5


# -------------------------------------------------------------------------------------- training
@dataclass
class TrainConfig:
    shards: str = "data/shards/simcol"
    latent_bank: str = "models/latent_bank.pt"
    out: str = "models/endoflow.pt"
    metrics: str = "metrics/train.json"
    plots: str = "plots/train"
    epochs: int = 20
    batch_size: int = 12
    lr: float = 1e-4
    weight_decay: float = 1e-3
    # adamw: decoupled weight decay. adam: decay added to the gradient (L2), which Adam's normalisation
    # inflates wherever the photometric gradient is small; on the default data it stalls learning.
    optimizer: Literal["adam", "adamw"] = "adamw"
    log_every: int = 10
    # Learning-rate schedule: constant, or step (x gamma every step_epochs, Monodepth2's), or cosine.
    schedule: Literal["constant", "step", "cosine"] = "step"
    step_epochs: int = 15
    gamma: float = 0.1
    grad_clip: Optional[float] = None  # max gradient norm; null: no clipping
    steps_per_epoch: Optional[int] = None  # cap per epoch (smoke runs); null: one pass over the shards
    val_batches: Optional[int] = None  # cap on validation batches per epoch; null: the whole val split
    bf16: bool = True  # bf16 autocast and channels-last on GPU (ignored on CPU)
    image_examples: int = 3  # fixed val frames whose depth is logged beside GT each epoch


@dataclass
class RayConfig:
    address: Optional[str] = None  # null: local Ray sized for this machine; "auto": join a cluster
    num_workers: int = 1
    use_gpu: bool = False
    cpus_per_worker: float = 1.0
    # Checkpoints: a local path (made absolute), a shared filesystem or an fsspec URL (s3://, file://...).
    storage_path: str = "ray_results"
    # Local Ray only (address null): logical CPUs (null: this machine's) and object store size.
    num_cpus: Optional[int] = None
    object_store_mb: int = 256
    run_name: str = "endoflow-train"  # + a fingerprint of params and data: same inputs resume the run


# --------------------------------------------------------------------------------------- evaluation
@dataclass
class EvalSetConfig:
    """One test set: samples of `split` in `<eval.shards>/<dataset>` whose group/sequence match."""

    dataset: str
    groups: list[str] = field(default_factory=list)  # empty: any group
    sequences: list[str] = field(default_factory=list)  # empty: any sequence
    split: str = "test"


def _default_test_sets() -> dict[str, EvalSetConfig]:
    return {
        "simcol_12": EvalSetConfig("simcol", groups=["SyntheticColon_I", "SyntheticColon_II"]),
        "simcol_3": EvalSetConfig("simcol", groups=["SyntheticColon_III"]),
        "endoslam_colon": EvalSetConfig("endoslam", groups=["Colon"]),
        "endoslam_small_intestine": EvalSetConfig("endoslam", groups=["Small Intestine"]),
    }


@dataclass
class EvalConfig:
    model: str = "models/endoflow.pt"
    shards: str = "data/shards"  # holds <dataset>/ shard folders; a local path or an fsspec URL
    metrics: str = "metrics/eval"  # <metrics>/<testset>.json
    plots: str = "plots/eval"  # <plots>/<testset>/
    predictions: str = "predictions"  # <predictions>/<testset>/ in the SimCol3D challenge layout
    test_sets: dict[str, EvalSetConfig] = field(default_factory=_default_test_sets)
    batch_size: int = 8
    depth_examples: int = 3  # frames shown with error maps per test set
    max_frames_per_sequence: Optional[int] = None  # null: every frame


# ----------------------------------------------------------------------------------------- tracking
@dataclass
class TrackingConfig:
    # null: embedded SQLite store at <project>/mlflow.db with artifacts in <project>/mlartifacts.
    uri: Optional[str] = None
    experiment: str = "endoflow"
    latent_bank_experiment: str = "endoflow-latent-bank"


# ---------------------------------------------------------------------------------------------- all
@dataclass
class Params:
    seed: int = 0
    data: DataConfig = field(default_factory=DataConfig)
    synth: SynthConfig = field(default_factory=SynthConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    latent_bank: LatentBankConfig = field(default_factory=LatentBankConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    ray: RayConfig = field(default_factory=RayConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


# ----------------------------------------------------------------------------------------- loading
def load_params(path: str | Path = "params.yaml", overrides: Sequence[str] = ()) -> Params:
    """Read ``path`` and apply ``key=value`` overrides (values parsed as YAML), then validate.

    Raises:
        ConfigError: naming the file and the dotted key that is unknown or mistyped.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: parameter file not found")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(raw).__name__}")
    for item in overrides:
        apply_override(raw, item)
    try:
        return params_from_dict(raw)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def params_from_dict(raw: dict[str, Any]) -> Params:
    """Validate a plain mapping (as parsed from YAML) into :class:`Params`."""
    return _build(Params, raw, prefix="")


def apply_override(raw: dict[str, Any], item: str) -> None:
    """Set ``a.b.c=value`` in a nested mapping; the value is parsed as YAML (``true``, ``[1, 2]``...)."""
    key, sep, value = item.partition("=")
    if not sep or not key:
        raise ConfigError(f"override {item!r}: expected key=value")
    node = raw
    parts = key.split(".")
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {item!r}: {part!r} is not a section")
        node = child
    node[parts[-1]] = yaml.safe_load(value)


def flatten_params(params: Any, prefix: str = "") -> dict[str, Any]:
    """Flat ``{"model.latent_bank": True, "eval.test_sets.simcol_3.groups": [...], ...}`` view.

    Reaches into nested sections and mappings of sections (such as ``eval.test_sets``); used for MLflow
    params and for the training fingerprint.
    """
    if dataclasses.is_dataclass(params):
        items = [(f.name, getattr(params, f.name)) for f in dataclasses.fields(params)]
    else:
        items = list(params.items())
    flat: dict[str, Any] = {}
    for name, value in items:
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(value) or isinstance(value, dict):
            flat.update(flatten_params(value, prefix=f"{key}."))
        else:
            flat[key] = value
    return flat


def params_to_dict(params: Any) -> dict[str, Any]:
    """Nested plain-dict form, for writing back to YAML or JSON."""
    return dataclasses.asdict(params)


def _build(cls: type, raw: Any, prefix: str) -> Any:
    if not isinstance(raw, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'params'}: expected a mapping, got {raw!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        raise ConfigError(f"unknown key {prefix}{unknown[0]!s} (known: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        if f.name in raw:
            kwargs[f.name] = _coerce(hints[f.name], raw[f.name], key)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"missing key {key}")
    return cls(**kwargs)


def _coerce(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, prefix=f"{key}.")
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(arg, value, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{key}: {value!r} matches none of {args}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{key} must be one of {list(args)}, got {value!r}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key} must be a list, got {value!r}")
        item_type = args[0] if args else Any
        return [_coerce(item_type, v, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key} must be a mapping, got {value!r}")
        value_type = args[1] if len(args) == 2 else Any
        return {str(k): _coerce(value_type, v, f"{key}.{k}") for k, v in value.items()}
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} must be an integer, got {value!r}")
        return value
    if tp is float:
        # PyYAML (YAML 1.1) reads `1e-4` as a string; accept what float() reads as a number.
        number = _float_or_none(value) if isinstance(value, str) else value
        if number is None or isinstance(number, bool) or not isinstance(number, (int, float)):
            raise ConfigError(f"{key} must be a number, got {value!r}")
        return float(number)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported parameter type {tp!r}")


def _float_or_none(text: str) -> Optional[float]:
    try:
        return float(text)
    except ValueError:
        return None
