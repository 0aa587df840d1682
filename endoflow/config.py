"""Typed configuration: ``params.yaml`` validated once into dataclasses.

Every stage and command reads its settings through :func:`load_params`. Unknown keys, values of the wrong
type, values out of range (``train.lr: -0.1``) and settings that contradict each other (``ray.num_workers``
CPUs beyond ``ray.num_cpus``) fail with :class:`ConfigError` naming the dotted key (``model.latent_bank``),
so a mistake in ``params.yaml`` or ``dvc exp run -S`` fails at load, never minutes into a stage. Keys left
out take the defaults below.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from functools import reduce
from typing import Any, Callable, Literal, Optional, Sequence, Union

import yaml


class ConfigError(ValueError):
    """A parameter is unknown, missing or of the wrong type; the message names the key."""


# What a device key may say, and what a precision key may say; endoflow/devices.py turns them into torch terms.
DEVICE_NAME = re.compile(r"auto|cpu|cuda(:[0-9]+)?")
Precision = Literal["auto", "bf16", "float32"]


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
    # Rendering device: auto (a CUDA GPU if torch sees one, else the CPU), cpu, cuda or cuda:N (endoflow.devices).
    # A GPU renders in one process, and its float arithmetic may differ from the CPU's in the last bits.
    device: str = "cpu"
    simcol: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(15, 60))
    endoslam: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(2, 120))
    scenenet: SynthLayoutConfig = field(default_factory=lambda: SynthLayoutConfig(60, 20))


# ---------------------------------------------------------------------------------------- preprocess
@dataclass
class PreprocessConfig:
    # A local path or an fsspec URL (file:///shared/shards, s3://bucket/shards) that every Ray node can write.
    out: str = "data/shards"
    # Who writes the shards: local (preprocess.workers processes on this machine) or ray (one Ray task per
    # shard on the cluster at ray.address, or on a local Ray when it is null; the dataset root must be at the
    # same path on every node). Both write the same bytes.
    engine: Literal["local", "ray"] = "local"
    workers: int = 2  # processes of the local engine
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
    metrics: str = "metrics/latent_bank.json"  # SWD before and after training, steps, seconds
    plots: str = "plots/latent_bank"  # sample grids and loss curves
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
    # Decay of the generator's weight average; its horizon (about 1 / (1 - decay) steps) must be short beside
    # the last stage, or the average still holds coarser stages' weights: 0.999 over 300-step stages left the
    # SWD ratio at 0.50-0.60 for seeds 0-2, 0.99 gives 0.43-0.45 (docs/method.md).
    ema_decay: float = 0.99
    # Initial scale of the synthesis convolutions relative to PyTorch's default; they are scale-free (AdaIN
    # follows), so below 1 they learn faster at the fixed lr (see endoflow.models.latent_bank.InitScaled).
    conv_init_scale: float = 0.25
    swd_samples: int = 256
    drift_weight: float = 0.001  # ProGAN's penalty on squared real scores, keeps critic outputs bounded
    fade_fraction: float = 0.5  # share of each new stage spent fading the new resolution in
    # Maps are centred log-depth divided by this (natural-log units), clipped to [-1, 1].
    depth_log_range: float = 1.5
    holdout_fraction: float = 0.1  # held out of train for the SWD when the shards have no val split
    device: str = "auto"  # auto, cpu, cuda or cuda:N (endoflow.devices); the bank file is saved as CPU tensors
    # float32 by default, also on GPUs: the gradient penalty differentiates the critic twice, and bf16 moves it
    # most (critic loss up to 6% off float32 at a first step); bf16 pretraining is unmeasured on a GPU
    # (docs/method.md, "Devices and precision"). auto or bf16 as for train.precision.
    precision: Precision = "float32"


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
    # With pose_vae, training warps with the reparameterised sample (true, the paper) or with the mean (false:
    # the KL still applies); the VAE study in docs/method.md separates the two. Evaluation always uses the mean.
    pose_sample: bool = True


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
    # auto: bf16 autocast (and channels-last) on a GPU with native bf16, float32 elsewhere; bf16 also runs on
    # the CPU (CI does). The device is Ray's (ray.use_gpu). See endoflow.devices.
    precision: Precision = "auto"
    image_examples: int = 3  # fixed val frames whose depth is logged beside GT each epoch
    # Ray checkpoints kept (the newest; each holds the best epoch's weights too, so the model is never lost)
    keep_checkpoints: int = 2
    # Processes per Ray worker that read, check, decode and collate its batches (0: the training process does,
    # between steps). The batch order depends on it (0 and 1 agree), so a run resumes only with its value. With
    # loader processes, loader_workers + 1 (the training process) must fit ray.cpus_per_worker.
    loader_workers: int = 0


@dataclass
class RayConfig:
    address: Optional[str] = None  # null: local Ray sized for this machine; "auto": join a cluster
    num_workers: int = 1
    use_gpu: bool = False
    cpus_per_worker: float = 1.0
    # Where Ray puts the workers: PACK / SPREAD as few / as many nodes as it can, STRICT_PACK all on one node,
    # STRICT_SPREAD each on a node of its own (Ray Train's ScalingConfig.placement_strategy).
    placement_strategy: Literal["PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD"] = "PACK"
    # Worker failures (a process or node lost, or any error a worker raises) that Ray Train recovers from by
    # restarting every worker from the newest checkpoint; -1: no limit. A real error is raised after max_failures
    # retries, each repeating at most the epoch it broke in.
    max_failures: int = 2
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
    split: Literal["train", "val", "test"] = "test"


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
    device: str = "auto"  # auto, cpu, cuda or cuda:N (endoflow.devices)
    precision: Precision = "auto"  # as train.precision; depth and pose are scored in float32 after the network


# ------------------------------------------------------------------------------------- reconstruction
@dataclass
class ReconstructSequenceConfig:
    """One sequence the ``reconstruct`` stage reconstructs and measures: ``sequence`` of ``data.<dataset>.root``
    (a name its reader lists), frames ``start, start + stride, ...`` below ``stop`` (null: to the end)."""

    dataset: str
    sequence: str
    start: int = 0
    stop: Optional[int] = None
    stride: int = 1


def _default_reconstructions() -> dict[str, ReconstructSequenceConfig]:
    return {
        "simcol_S5": ReconstructSequenceConfig("simcol", "S5"),
        "simcol_O1": ReconstructSequenceConfig("simcol", "O1"),
        "endoslam_colon": ReconstructSequenceConfig("endoslam", "UnityCam/Colon"),
    }


@dataclass
class ReconstructConfig:
    model: str = "models/endoflow.pt"
    out: str = "reconstructions"  # <out>/<name>/: what `endoflow reconstruct` writes
    metrics: str = "metrics/reconstruct"  # <metrics>/<name>.json: path and surface errors against ground truth
    plots: str = "plots/reconstruct"  # <plots>/<name>/: the picture sheet and per-frame path errors
    sequences: dict[str, ReconstructSequenceConfig] = field(default_factory=_default_reconstructions)
    size: Optional[int] = None  # null: the model's data.size
    voxel_cm: Optional[float] = None  # null: about one pixel's footprint at a quarter of the depth range
    trunc_cm: Optional[float] = None  # null: 4 voxels
    device: str = "auto"


# ----------------------------------------------------------------------------------------- tracking
@dataclass
class TrackingConfig:
    # null: embedded SQLite store at <project>/mlflow.db with artifacts in <project>/mlartifacts.
    uri: Optional[str] = None
    experiment: str = "endoflow"
    latent_bank_experiment: str = "endoflow-latent-bank"
    # a name: each training registers its model as a new version of this MLflow registered model
    # (models:/<name>/<version>, which `endoflow reconstruct --model` and eval.model accept); null: not registered
    registered_model: Optional[str] = None


# The datasets endoflow reads, one per section of ``data``: the one list every command, stage, reader and
# writer takes. SceneNet is read for its depth alone (the latent bank): its shards hold no triplets.
DATASETS = tuple(name for name, tp in typing.get_type_hints(DataConfig).items() if dataclasses.is_dataclass(tp))
DEPTH_ONLY_DATASETS = frozenset({"scenenet"})


# ---------------------------------------------------------------------------------------------- all
@dataclass
class Params:
    seed: int = 0
    # torch's CPU threads in every process that computes (pretraining, each training worker, evaluation,
    # reconstruction): float sums split over threads add in another order, so the same seed gives other numbers
    # with another count; a fixed count, not the machine's cores, makes them the same on any machine
    threads: int = 2
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
    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)


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
    """Validate a plain mapping (as parsed from YAML) into :class:`Params`: types, ranges, cross-field rules."""
    params = _build(Params, raw, prefix="")
    _check_ranges(params)
    for check in _CROSS_FIELD_CHECKS:
        check(params)
    return params


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
        if not math.isfinite(number):
            raise ConfigError(f"{key} must be a finite number, got {value!r}")
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


# -------------------------------------------------------------------------------------- validation
@dataclass(frozen=True)
class _Check:
    """A condition on one value, and the words an error uses for it (``train.lr must be > 0, got -0.1``)."""

    holds: Callable[[Any], bool]
    expected: str


@dataclass(frozen=True)
class _Each:
    """``check`` on every entry of a list, or on the value itself when it is one number."""

    check: _Check


def _at_least(bound: float) -> _Check:
    return _Check(lambda v: v >= bound, f">= {bound}")


def _above(bound: float) -> _Check:
    return _Check(lambda v: v > bound, f"> {bound}")


def _within(low: float, high: float, include_low: bool = True, include_high: bool = True) -> _Check:
    """``low <= v <= high``, either end excluded on request; stated as ``in [low, high)`` and the like."""
    return _Check(
        lambda v: (low <= v if include_low else low < v) and (v <= high if include_high else v < high),
        f"in {'[' if include_low else '('}{low}, {high}{']' if include_high else ')'}",
    )


def _optional(check: _Check) -> _Check:
    return _Check(lambda v: v is None or check.holds(v), f"null or {check.expected}")


def _is_power_of_two(value: int) -> bool:
    return value >= 1 and value & (value - 1) == 0


def _is_plain_name(name: str) -> bool:
    return bool(name) and all(c.isascii() and (c.isalnum() or c in "_-") for c in name)


_COUNT = _at_least(1)
_POSITIVE = _above(0)
_NON_NEGATIVE = _at_least(0)
_FRACTION = _within(0, 1)
_PROPER_FRACTION = _within(0, 1, include_high=False)
_DEVICE = _Check(lambda v: DEVICE_NAME.fullmatch(v) is not None, "auto, cpu, cuda or cuda:N")
# The ResNet encoder downsamples by 32, and DepthNet needs whole feature maps at every level.
ENCODER_STRIDE = 32
# pretrain.py measures the bank with a sliced Wasserstein distance on pyramids down to 16 px.
SWD_MIN_RESOLUTION = 16
# Ray refuses smaller object stores (ray._private.ray_constants.OBJECT_STORE_MINIMUM_MEMORY_BYTES, 75 MiB).
_RAY_MIN_OBJECT_STORE_MB = 75

_TOP_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    # numpy seeds (the loader's shard order, the synthetic scenes) must be non-negative.
    ("seed", _NON_NEGATIVE),
    ("threads", _COUNT),
)

_DATA_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("data.size", _Check(lambda v: v >= ENCODER_STRIDE and v % ENCODER_STRIDE == 0,
                         f"a positive multiple of {ENCODER_STRIDE} (the ResNet encoder downsamples by that)")),
    ("data.simcol.reference_size", _COUNT),
    ("data.endoslam.unitycam_translation_to_cm", _POSITIVE),
    ("data.endoslam.camera_translation_to_cm", _POSITIVE),
    ("data.endoslam.depth_full_scale_cm", _POSITIVE),
    ("data.endoslam.fps", _POSITIVE),
    ("data.scenenet.max_frames_per_trajectory", _optional(_COUNT)),
)

_SYNTH_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("synth.size", _Check(lambda v: v >= 8, ">= 8 (the smallest frame the synthetic writers render)")),
    ("synth.seed", _NON_NEGATIVE),
    ("synth.workers", _COUNT),
    ("synth.device", _DEVICE),
    ("synth.simcol.sequences", _COUNT),
    ("synth.endoslam.sequences", _COUNT),  # at most one per UnityCam organ: the writers check that
    ("synth.scenenet.sequences", _COUNT),
    # Two frames make the shortest trajectory the writers render; triplets need more (a cross-field rule).
    ("synth.simcol.frames", _at_least(2)),
    ("synth.endoslam.frames", _at_least(2)),
    ("synth.scenenet.frames", _at_least(2)),
)

_PREPROCESS_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("preprocess.workers", _COUNT),
    ("preprocess.samples_per_shard", _COUNT),
    ("preprocess.shard_multiple", _COUNT),
    ("preprocess.neighbour_offset", _COUNT),
)

_LATENT_BANK_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("latent_bank.resolution", _Check(lambda v: _is_power_of_two(v) and v >= SWD_MIN_RESOLUTION,
                                     f"a power of two >= {SWD_MIN_RESOLUTION} (pretraining's SWD needs "
                                     f"{SWD_MIN_RESOLUTION} px)")),
    ("latent_bank.start_resolution", _Check(lambda v: _is_power_of_two(v) and v >= 4, "a power of two >= 4")),
    ("latent_bank.latent_dim", _COUNT),
    ("latent_bank.style_dim", _COUNT),
    ("latent_bank.mapping_layers", _COUNT),
    ("latent_bank.channel_base", _COUNT),
    ("latent_bank.channel_max", _COUNT),
    ("latent_bank.batch_size", _COUNT),
    ("latent_bank.steps_per_stage", _Each(_COUNT)),
    ("latent_bank.lr", _POSITIVE),
    ("latent_bank.betas", _Check(lambda v: len(v) == 2, "two numbers [beta1, beta2]")),
    ("latent_bank.betas", _Each(_PROPER_FRACTION)),
    ("latent_bank.n_critic", _Each(_COUNT)),
    ("latent_bank.gp_gamma", _NON_NEGATIVE),
    ("latent_bank.ema_decay", _PROPER_FRACTION),
    ("latent_bank.conv_init_scale", _POSITIVE),
    ("latent_bank.swd_samples", _COUNT),
    ("latent_bank.drift_weight", _NON_NEGATIVE),
    ("latent_bank.fade_fraction", _FRACTION),
    ("latent_bank.depth_log_range", _POSITIVE),
    ("latent_bank.holdout_fraction", _PROPER_FRACTION),
    ("latent_bank.device", _DEVICE),
)

_MODEL_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("model.min_depth", _POSITIVE),
    # DepthNet's decoder has five levels; disparities come from the four finest (Monodepth2's scales).
    ("model.scales", _within(1, 4)),
)

_LOSS_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("loss.ssim_weight", _FRACTION),
    ("loss.smoothness_weight", _NON_NEGATIVE),
    ("loss.kl_weight", _NON_NEGATIVE),
)

_TRAIN_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("train.epochs", _COUNT),
    ("train.batch_size", _COUNT),
    ("train.lr", _POSITIVE),
    ("train.weight_decay", _NON_NEGATIVE),
    ("train.log_every", _COUNT),
    ("train.step_epochs", _COUNT),
    ("train.gamma", _within(0, 1, include_low=False)),
    ("train.grad_clip", _optional(_POSITIVE)),
    ("train.steps_per_epoch", _optional(_COUNT)),
    ("train.val_batches", _optional(_COUNT)),
    ("train.image_examples", _NON_NEGATIVE),
    ("train.keep_checkpoints", _COUNT),  # Ray's CheckpointConfig refuses to keep none
    ("train.loader_workers", _NON_NEGATIVE),
)

_RAY_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("ray.num_workers", _COUNT),
    ("ray.cpus_per_worker", _POSITIVE),
    ("ray.num_cpus", _optional(_COUNT)),
    ("ray.object_store_mb", _at_least(_RAY_MIN_OBJECT_STORE_MB)),
    ("ray.max_failures", _at_least(-1)),  # -1: Ray Train retries without limit
)

_EVAL_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("eval.batch_size", _COUNT),
    ("eval.depth_examples", _NON_NEGATIVE),
    ("eval.max_frames_per_sequence", _optional(_COUNT)),
    ("eval.device", _DEVICE),
)

_RECONSTRUCT_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    ("reconstruct.size", _optional(_Check(lambda v: v >= ENCODER_STRIDE and v % ENCODER_STRIDE == 0,
                                          f"a positive multiple of {ENCODER_STRIDE}"))),
    ("reconstruct.voxel_cm", _optional(_POSITIVE)),
    ("reconstruct.trunc_cm", _optional(_POSITIVE)),
    ("reconstruct.device", _DEVICE),
)

_TRACKING_RULES: tuple[tuple[str, _Check | _Each], ...] = (
    # MLflow's registry takes other characters too, but a models:/<name>/<version> URI must parse back
    ("tracking.registered_model", _optional(_Check(_is_plain_name, "a name of letters, digits, _ and -"))),
)

_RANGE_RULES = (_TOP_RULES + _DATA_RULES + _SYNTH_RULES + _PREPROCESS_RULES + _LATENT_BANK_RULES + _MODEL_RULES
                + _LOSS_RULES + _TRAIN_RULES + _RAY_RULES + _EVAL_RULES + _RECONSTRUCT_RULES + _TRACKING_RULES)


def _check_ranges(params: Params) -> None:
    for key, rule in _RANGE_RULES:
        value = reduce(getattr, key.split("."), params)
        if isinstance(rule, _Each):
            for item_key, item in _entries(key, value):
                _require(item_key, item, rule.check)
        else:
            _require(key, value, rule)


def _entries(key: str, value: Any) -> list[tuple[str, Any]]:
    if isinstance(value, list):
        return [(f"{key}[{i}]", item) for i, item in enumerate(value)]
    return [(key, value)]


def _require(key: str, value: Any, check: _Check) -> None:
    if not check.holds(value):
        raise ConfigError(f"{key} must be {check.expected}, got {value!r}")


# --------------------------------------------------------------------------------- cross-field rules
def _check_depth_range(params: Params) -> None:
    model = params.model
    if model.min_depth >= model.max_depth:
        raise ConfigError(f"model.min_depth ({model.min_depth}) must be below model.max_depth ({model.max_depth})")


def _check_encoder_batch_norm(params: Params) -> None:
    # At the smallest size the encoder's last features are 1x1, and BatchNorm in training mode needs more
    # than one value per channel: a batch of one fails at the first step.
    if params.data.size == ENCODER_STRIDE and params.train.batch_size < 2:
        raise ConfigError(
            f"train.batch_size must be >= 2 when data.size is {ENCODER_STRIDE} (the encoder's 1x1 features give "
            f"BatchNorm one value per channel), got {params.train.batch_size}"
        )


def _bank_resolutions(cfg: LatentBankConfig) -> list[int]:
    """The generator's block resolutions, ``start_resolution`` doubling up to ``resolution``."""
    resolutions = [cfg.start_resolution]
    while resolutions[-1] < cfg.resolution:
        resolutions.append(resolutions[-1] * 2)
    return resolutions


def _check_bank_growth(params: Params) -> None:
    cfg = params.latent_bank
    if cfg.start_resolution > cfg.resolution:
        raise ConfigError(
            f"latent_bank.start_resolution ({cfg.start_resolution}) must not exceed latent_bank.resolution "
            f"({cfg.resolution})"
        )
    resolutions = _bank_resolutions(cfg)
    for name in ("steps_per_stage", "n_critic"):
        value = getattr(cfg, name)
        if isinstance(value, list) and len(value) != len(resolutions):
            raise ConfigError(
                f"latent_bank.{name} must be one number or a list of {len(resolutions)} (one per resolution "
                f"{resolutions}), got {value}"
            )


def _check_synth_triplets(params: Params) -> None:
    offset = params.preprocess.neighbour_offset
    for layout in (name for name in DATASETS if name not in DEPTH_ONLY_DATASETS):
        frames = getattr(params.synth, layout).frames
        if frames <= 2 * offset:
            raise ConfigError(
                f"synth.{layout}.frames must exceed 2 x preprocess.neighbour_offset = {2 * offset} (a sample needs "
                f"frames cur - {offset} and cur + {offset}), got {frames}"
            )


def _check_ray_fits_local_cpus(params: Params) -> None:
    ray = params.ray
    if ray.address or ray.num_cpus is None:  # connect_ray starts a local Ray for an empty address too
        return
    need = ray.num_workers * ray.cpus_per_worker
    if need > ray.num_cpus:
        raise ConfigError(
            f"ray.num_workers x ray.cpus_per_worker = {ray.num_workers} x {ray.cpus_per_worker:g} = {need:g} CPUs "
            f"exceed ray.num_cpus = {ray.num_cpus} of the local Ray (ray.address null); Ray would wait forever"
        )


def _check_workers_have_shards(params: Params) -> None:
    # Otherwise a worker finds no shard of its own (loader.rank_shards) once training or validation starts.
    ray, preprocess = params.ray, params.preprocess
    if ray.num_workers > preprocess.shard_multiple:
        raise ConfigError(
            f"ray.num_workers ({ray.num_workers}) must not exceed preprocess.shard_multiple "
            f"({preprocess.shard_multiple}): a split has a multiple of {preprocess.shard_multiple} shards, maybe "
            f"just {preprocess.shard_multiple}, and every worker needs a shard of its own"
        )


def _check_loader_workers_fit_worker_cpus(params: Params) -> None:
    # Loader processes run beside the training process inside the CPUs Ray reserves for the worker; beyond
    # them they would take cores from other workers or trials on the node.
    loaders, cpus = params.train.loader_workers, params.ray.cpus_per_worker
    if loaders and loaders + 1 > cpus:
        raise ConfigError(
            f"train.loader_workers ({loaders}) + 1 (the training process) = {loaders + 1} CPUs exceed "
            f"ray.cpus_per_worker = {cpus:g}; raise ray.cpus_per_worker or lower train.loader_workers"
        )


def _check_test_sets(params: Params) -> None:
    known = list(DATASETS)
    for name, test_set in params.eval.test_sets.items():
        if not _is_plain_name(name):
            raise ConfigError(f"eval.test_sets: name {name!r} must be letters, digits, _ and - only (it names a "
                              f"DVC stage, folders and dotted keys)")
        if test_set.dataset not in known:
            raise ConfigError(f"eval.test_sets.{name}.dataset must be one of {known}, got {test_set.dataset!r}")


def _check_reconstructions(params: Params) -> None:
    known = [name for name in DATASETS if name not in DEPTH_ONLY_DATASETS]
    for name, item in params.reconstruct.sequences.items():
        key = f"reconstruct.sequences.{name}"
        if not _is_plain_name(name):
            raise ConfigError(f"reconstruct.sequences: name {name!r} must be letters, digits, _ and - only (it "
                              f"names a DVC stage and folders)")
        if item.dataset not in known:
            raise ConfigError(f"{key}.dataset must be one of {known} (datasets with images), got {item.dataset!r}")
        _require(f"{key}.start", item.start, _NON_NEGATIVE)
        _require(f"{key}.stride", item.stride, _COUNT)
        if item.stop is not None and item.stop <= item.start:
            raise ConfigError(f"{key}.stop must be above {key}.start ({item.start}) or null, got {item.stop}")


_CROSS_FIELD_CHECKS: tuple[Callable[[Params], None], ...] = (
    _check_depth_range,
    _check_encoder_batch_norm,
    _check_bank_growth,
    _check_synth_triplets,
    _check_ray_fits_local_cpus,
    _check_workers_have_shards,
    _check_loader_workers_fit_worker_cpus,
    _check_test_sets,
    _check_reconstructions,
)
