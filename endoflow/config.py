"""The parameters: one pydantic schema, the one source of every default, range and unit.

``params.yaml`` equals the schema's defaults (``endoflow params`` writes it; a test holds them equal), presets
in ``presets/`` state only their differences, and :func:`load_params` validates a file once: an unknown key, a
value of the wrong type or out of range, or settings that contradict each other fail with :class:`ConfigError`
naming the dotted key, the value and what was expected. Each field says whether it changes what training
computes (:func:`training_keys`), which is what the resume fingerprint covers.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Annotated, Any, Callable, ClassVar, Literal, Optional, Sequence, Union, get_args

from typing_extensions import Self

import yaml
from pydantic import (AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, PlainValidator, ValidationError,
                      model_validator)
from pydantic_core import PydanticCustomError


class ConfigError(ValueError):
    """A parameter is unknown, missing or of the wrong type; the message names the key."""


# The ResNet encoder downsamples by 32, and DepthNet needs whole feature maps at every level.
ENCODER_STRIDE = 32
# pretrain.py measures the bank with a sliced Wasserstein distance on pyramids down to 16 px.
SWD_MIN_RESOLUTION = 16
# Ray refuses smaller object stores (ray._private.ray_constants.OBJECT_STORE_MINIMUM_MEMORY_BYTES, 75 MiB).
RAY_MIN_OBJECT_STORE_MB = 75
# What a device key may say; endoflow/devices.py turns it into a torch device.
DEVICE_NAME = re.compile(r"auto|cpu|cuda(:[0-9]+)?")
Precision = Literal["auto", "bf16", "float32"]
PRECISIONS: tuple[str, ...] = get_args(Precision)
Compile = Union[Literal["auto"], bool]
Split = Literal["train", "val", "test"]


# ------------------------------------------------------------------------------------------ field types
def _expect(holds: Callable[[Any], bool], expected: str) -> AfterValidator:
    """A check whose failure reads ``<key> must be <expected>, got <value>``."""

    def check(value: Any) -> Any:
        if not holds(value):
            raise PydanticCustomError("expected", "{expected}", {"expected": expected})
        return value

    return AfterValidator(check)


def _yaml_number(value: Any) -> Any:
    # PyYAML (YAML 1.1) reads `1e-4` as a string; accept what float() reads as a number.
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _count_or_counts(value: Any) -> Any:
    """One integer >= 1, or a non-empty list of them (one per resolution of the latent bank)."""
    if not isinstance(value, list):
        if not _is_count(value):
            raise PydanticCustomError("expected", "{expected}", {"expected": "an integer >= 1 or a list of them"})
        return value
    if not value:
        raise PydanticCustomError("expected", "{expected}", {"expected": "an integer >= 1 or a non-empty list"})
    for index, item in enumerate(value):
        if not _is_count(item):
            raise PydanticCustomError("entry", "{expected}", {"index": index, "expected": "an integer >= 1",
                                                              "value": repr(item)})
    return value


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def _is_power_of_two(value: int) -> bool:
    return value >= 1 and value & (value - 1) == 0


def _is_plain_name(name: str) -> bool:
    return bool(name) and all(c.isascii() and (c.isalnum() or c in "_-") for c in name)


Number = Annotated[float, BeforeValidator(_yaml_number)]
Device = Annotated[str, _expect(lambda v: DEVICE_NAME.fullmatch(v) is not None, "auto, cpu, cuda or cuda:N")]
ImageSize = Annotated[int, _expect(lambda v: v >= ENCODER_STRIDE and v % ENCODER_STRIDE == 0,
                                   f"a positive multiple of {ENCODER_STRIDE} (the ResNet encoder downsamples by "
                                   f"that)")]
Count = Annotated[int, Field(ge=1)]
CountOrCounts = Annotated[Union[int, list[int]], PlainValidator(_count_or_counts)]
Intrinsics = Optional[Annotated[list[list[Number]],
                                _expect(lambda rows: len(rows) == 3 and all(len(row) == 3 for row in rows),
                                        "a 3x3 matrix (three rows of three numbers)")]]
Region = Optional[Annotated[list[int], _expect(
    lambda v: len(v) == 4 and v[0] >= 0 and v[1] >= 0 and v[2] >= 1 and v[3] >= 1,
    "[x, y, width, height] in whole pixels, x and y >= 0, width and height >= 1")]]
PlainName = Annotated[str, _expect(_is_plain_name, "a name of letters, digits, _ and -")]


def setting(default: Any = ..., doc: str = "", *, unit: Optional[str] = None, training: Optional[bool] = None,
            **constraints: Any) -> Any:
    """A field with its default, what it means, its unit and whether it changes what training computes (``None``:
    as its section says); ``constraints`` are pydantic's (``ge``, ``gt``, ``le``, ``lt``)."""
    factory = constraints.pop("default_factory", None)
    extra = {"unit": unit, "training": training}
    if factory is not None:
        return Field(default_factory=factory, description=doc, json_schema_extra=extra, **constraints)
    return Field(default, description=doc, json_schema_extra=extra, **constraints)


class Section(BaseModel):
    """A section of params.yaml: unknown keys refused, types strict (``true`` is no integer), numbers finite."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, validate_default=True)
    # Whether the section's fields change what training computes, unless a field says otherwise; None: as the
    # section holding it.
    TRAINING: ClassVar[Optional[bool]] = None

    def replace(self, **changes: Any) -> Self:
        """A copy with ``changes`` applied, validated as a file's values are (``params.train.replace(lr=1e-3)``)."""
        try:
            return type(self).model_validate({**dict(self), **changes})
        except ValidationError as exc:
            where = section_path(type(self))
            raise ConfigError("; ".join(_describe(error, type(self), where) for error in exc.errors())) from None


# ------------------------------------------------------------------------------------------------ data
class SimColConfig(Section):
    root: str = setting("data/raw/synthetic/SimCol3D", "SimCol3D root (the native layout)")
    intrinsics: Intrinsics = setting(None, "3x3 pixel K at reference_size, overriding cam.txt (row-major); null "
                                           "reads cam.txt", unit="px")
    reference_size: Count = setting(475, "the image width cam.txt describes; K is scaled by stored width / this",
                                    unit="px")
    val: list[str] = setting(["S4", "S9", "S14", "B4", "B9", "B14"], "sequences of the val split")
    test: list[str] = setting(["S5", "S10", "S15", "B5", "B10", "B15", "O1", "O2", "O3"],
                              "sequences of the test split")


class EndoSLAMConfig(Section):
    root: str = setting("data/raw/synthetic/EndoSLAM", "EndoSLAM root (the native layout)")
    layout: Literal["auto", "unitycam", "camera"] = setting(
        "auto", "unitycam: synthetic VR-Caps export; camera: real HighCam/LowCam/... recordings; auto: detect")
    unitycam_translation_to_cm: Number = setting(1.0, "UnityCam pose translation units to cm (unconfirmed)", gt=0)
    camera_translation_to_cm: Number = setting(100.0, "real-camera pose translation units to cm (sheets say m)",
                                               gt=0)
    depth_full_scale_cm: Number = setting(20.0, "the distance a UnityCam depth PNG's 255 stands for", unit="cm",
                                          gt=0)
    depth_is_ray_length: bool = setting(False, "depth PNGs hold distance along the ray, not z-depth")
    fps: Number = setting(30.0, "frame rate of the recordings", unit="Hz", gt=0)
    intrinsics: Intrinsics = setting(None, "3x3 pixel K for the stored frames; null uses the documented "
                                           "third-party UnityCam K (scaled)", unit="px")
    camera_poses_left_handed: bool = setting(False, "real-camera poses: convert from a left-handed frame like "
                                                    "UnityCam's")
    split: Split = setting("test", "the split every EndoSLAM sequence goes to")


class SceneNetConfig(Section):
    root: str = setting("data/raw/synthetic/SceneNet", "SceneNet RGB-D root (depth only: the latent bank)")
    max_frames_per_trajectory: Optional[Count] = setting(None, "cap per trajectory; null: every frame")


class C3VDConfig(Section):
    root: str = setting("data/raw/C3VD", "C3VD root: one folder per sequence (the native layout); not part of the "
                                         "default pipeline")
    calibration: str = setting("calibration/cfhq190l_omnidirectional_values.txt",
                               "the omnidirectional calibration's values, relative to the root (or absolute)")
    focal_px: Optional[Number] = setting(None, "focal length of the pinhole frames and depth are undistorted onto; "
                                               "null: the calibration's a0", unit="px", gt=0)
    val: list[str] = setting(default_factory=list, doc="sequences of the val split")
    test: list[str] = setting(default_factory=list, doc="sequences of the test split")


class VideoConfig(Section):
    """Unlabelled video: every video file and folder of images under ``root`` is a sequence
    (:mod:`endoflow.data.video`)."""

    root: str = setting("data/raw/synthetic/Video", "folder of videos (mp4, avi, mov, mkv) and/or folders of frames, "
                                                   "each a sequence; no depth, no poses")
    intrinsics: Optional[str] = setting(
        None, "K of the native frames for every sequence: a cam.txt, a YAML/JSON file (fx, fy, cx, cy, width, height) "
              "or 'fx,fy,cx,cy' (px); a sidecar <name>.intrinsics.{json,yaml,yml,txt} beside a sequence overrides "
              "it; null: unknown, assumed from data.assumed_fov_deg")
    crop: Region = setting(None, "[x, y, width, height] of the native frames to keep (one view of a side-by-side "
                                 "recording, an overlay left out); null: the whole frame", unit="px")
    fps: Optional[Number] = setting(None, "target frame rate: every round(native / fps)-th frame is kept; null: "
                                          "every frame", unit="Hz", gt=0)
    folder_fps: Number = setting(30.0, "frame rate of a folder of frames", unit="Hz", gt=0)
    val: list[str] = setting(default_factory=list, doc="sequences of the val split (whole)")
    test: list[str] = setting(default_factory=list, doc="sequences of the test split (whole)")
    val_share: Number = setting(0.2, "of every other sequence, the last share of its frames held out as the "
                                     "validation sequence <name>@val (a split by time)", ge=0, lt=1)


class DataConfig(Section):
    # the data reaches training through the shards, whose manifest (every shard's SHA-256) is in the fingerprint
    TRAINING: ClassVar[Optional[bool]] = False

    size: ImageSize = setting(64, "stored square size of shard images (centre crop to square, then resize)",
                              unit="px")
    # endoscopes see about 140 degrees across; training corrects it (model/intrinsics.py)
    assumed_fov_deg: Number = setting(140.0, "diagonal field of view of the centred pinhole assumed where a camera's "
                                             "intrinsics are unknown or withheld", unit="deg", gt=0, lt=180)
    simcol: SimColConfig = setting(default_factory=SimColConfig)
    endoslam: EndoSLAMConfig = setting(default_factory=EndoSLAMConfig)
    scenenet: SceneNetConfig = setting(default_factory=SceneNetConfig)
    c3vd: C3VDConfig = setting(default_factory=C3VDConfig)
    video: VideoConfig = setting(default_factory=VideoConfig)


# ----------------------------------------------------------------------------------------------- synth
class SynthLayoutConfig(Section):
    sequences: Count = setting(doc="sequences rendered")
    # Two frames make the shortest trajectory the writers render; triplets need more (a cross-field rule).
    frames: int = setting(doc="frames per sequence", ge=2)


class SynthTubeLayoutConfig(SynthLayoutConfig):
    test_frames: Optional[int] = setting(
        None, "frames of each test sequence, whose camera follows a script crossing every change of motion (a slow "
              "advance, a pause, a withdrawal, a fast advance, a turn); null: as frames", ge=2)


class SynthConfig(Section):
    # the data reaches training through the shards, whose manifest is hashed
    TRAINING: ClassVar[Optional[bool]] = False

    out: str = setting("data/raw/synthetic", "where the synthesize stage writes the native layouts")
    size: int = setting(128, "rendered square frame size", unit="px", ge=8)
    seed: int = setting(0, "seed of the procedural scenes", ge=0)
    workers: Count = setting(2, "processes rendering sequences in parallel (CPU)")
    device: Device = setting("cpu", "auto, cpu, cuda or cuda:N; a GPU renders in one process, its float "
                                    "arithmetic may differ from the CPU's in the last bits")
    # what real footage differs in, to measure adaptation with exact ground truth (docs/synthetic_data.md)
    look: Literal["built-in", "second"] = setting(
        "built-in", "second: the same scenes in a look the default model never trains on: paler, yellower mucosa, "
                    "darker corners, strong highlights, a circular field of view, a shorter focal length")
    # The default training sequences mostly advance (a 60-frame sequence is one phase two times in three), so the
    # data asks a pose network for one step; shorter phases make each training sequence cross phases.
    phase_frames: Optional[list[Count]] = setting(
        None, "how many frames one phase of the camera (advancing, withdrawing, pausing) lasts in every tube "
              "sequence but the scripted test ones, drawn per phase between the two; their scenes are drawn anew "
              "too; null: each scene's own (30 to 120)", unit="frames", min_length=2, max_length=2)
    simcol: SynthTubeLayoutConfig = setting(
        default_factory=lambda: SynthTubeLayoutConfig(sequences=15, frames=60, test_frames=120))
    # at most one sequence per UnityCam organ: the writers check that; with data.endoslam.split test, every one
    # is a test sequence
    endoslam: SynthTubeLayoutConfig = setting(default_factory=lambda: SynthTubeLayoutConfig(sequences=2, frames=120))
    scenenet: SynthLayoutConfig = setting(default_factory=lambda: SynthLayoutConfig(sequences=60, frames=20))
    # unlabelled: video files and frame folders seen through an endoscope's circle, for data.video
    video: SynthLayoutConfig = setting(default_factory=lambda: SynthLayoutConfig(sequences=2, frames=90))

    @model_validator(mode="after")
    def _phase_range(self) -> "SynthConfig":
        if self.phase_frames is not None and self.phase_frames[0] > self.phase_frames[1]:
            raise _field_error("phase_frames", "[shortest, longest] with shortest <= longest", self.phase_frames)
        return self


# ------------------------------------------------------------------------------------------ preprocess
class PreprocessConfig(Section):
    # as data: the shards' bytes are in the fingerprint, so how they were written (engine, workers) is not
    TRAINING: ClassVar[Optional[bool]] = False

    out: str = setting("data/shards", "a local path or an fsspec URL (file:///shared/shards, s3://bucket/shards) "
                                      "that every Ray node can write")
    engine: Literal["local", "ray"] = setting(
        "local", "local: preprocess.workers processes here; ray: one Ray task per shard at ray.address (the "
                 "dataset root at the same path on every node); both write the same bytes")
    workers: Count = setting(2, "processes of the local engine")
    samples_per_shard: Count = setting(128, "samples per shard file")
    shard_multiple: Count = setting(4, "each split's shard count is a multiple of this, so whole shards divide "
                                       "evenly over workers")
    neighbour_offset: Count = setting(1, "prev/next are frames cur -/+ this offset", unit="frames")
    # A mixture keeps consecutive pairs, the pairs the model is scored on, in training, while wider pairs carry
    # several frames' motion: a pose network that answers one step for every pair cannot fit them all.
    # to measure what training learns of them: the shards hold the assumed K, as for a camera nobody calibrated
    withhold_intrinsics: bool = setting(False, "store every sequence's K as unknown, assumed from "
                                               "data.assumed_fov_deg")
    train_offsets: Optional[list[Count]] = setting(
        None, "the train split's offsets, one per target frame in turn (its position in the sequence modulo their "
              "count); null: neighbour_offset", unit="frames", min_length=1)


# ----------------------------------------------------------------------------------------- latent bank
class LatentBankConfig(Section):
    """Generative pretraining of the StyleGAN-like depth generator (WGAN-GP, progressive growing)."""

    # the bank reaches training as its file, whose bytes are in the fingerprint
    TRAINING: ClassVar[Optional[bool]] = False

    shards: str = setting("data/shards/scenenet", "depth shards the bank learns from")
    out: str = setting("models/latent_bank.pt", "the bank file", training=False)
    metrics: str = setting("metrics/latent_bank.json", "SWD before and after training, steps, seconds",
                           training=False)
    plots: str = setting("plots/latent_bank", "sample grids and loss curves", training=False)
    resolution: int = setting(64, "final generator resolution", unit="px")
    start_resolution: int = setting(4, "first generator block; with resolution 64 the bank has 5 blocks, one per "
                                       "DepthNet encoder level", unit="px")
    latent_dim: Count = setting(128, "latent code size")
    style_dim: Count = setting(128, "style vector size")
    mapping_layers: Count = setting(4, "layers of the mapping network")
    channel_base: Count = setting(512, "a block has min(channel_base / resolution, channel_max) channels")
    channel_max: Count = setting(128, "most channels of a block")
    batch_size: Count = setting(16, "depth maps per step")
    steps_per_stage: CountOrCounts = setting(300, "generator steps at each resolution: one number for all, or a "
                                                  "list from start_resolution up")
    lr: Number = setting(1e-4, "learning rate, fixed as in the paper", gt=0)
    betas: list[Annotated[Number, Field(ge=0, lt=1)]] = setting(
        [0.0, 0.99], "Adam's [beta1, beta2]", min_length=2, max_length=2)
    n_critic: CountOrCounts = setting(1, "critic steps per generator step: one number, or a list like "
                                         "steps_per_stage")
    gp_gamma: Number = setting(10.0, "gradient-penalty weight", ge=0)
    # Its horizon (about 1 / (1 - decay) steps) must be short beside the last stage, or the average still holds
    # coarser stages' weights: 0.999 over 300-step stages left the SWD ratio at 0.50-0.60 for seeds 0-2, 0.99
    # gives 0.43-0.45 (docs/method.md).
    ema_decay: Number = setting(0.99, "decay of the generator's weight average", ge=0, lt=1)
    # They are scale-free (AdaIN follows), so below 1 they learn faster at the fixed lr
    # (see endoflow.models.latent_bank.InitScaled).
    conv_init_scale: Number = setting(0.25, "initial scale of the synthesis convolutions relative to PyTorch's "
                                            "default", gt=0)
    swd_samples: Count = setting(256, "maps the sliced Wasserstein distance compares")
    drift_weight: Number = setting(0.001, "ProGAN's penalty on squared real scores, keeps critic outputs bounded",
                                   ge=0)
    fade_fraction: Number = setting(0.5, "share of each new stage spent fading the new resolution in", ge=0, le=1)
    depth_log_range: Number = setting(1.5, "maps are centred log-depth divided by this, clipped to [-1, 1]",
                                      unit="natural-log units", gt=0)
    holdout_fraction: Number = setting(0.1, "held out of train for the SWD when the shards have no val split",
                                       ge=0, lt=1)
    device: Device = setting("auto", "auto, cpu, cuda or cuda:N; the bank file is saved as CPU tensors",
                             training=False)
    # The gradient penalty differentiates the critic twice, and bf16 moves it most (critic loss up to 6% off
    # float32 at a first step); bf16 pretraining is unmeasured on a GPU (docs/method.md, Devices and precision).
    precision: Precision = setting("float32", "float32, also on GPUs; auto or bf16 as for train.precision")

    @model_validator(mode="after")
    def _resolutions(self) -> "LatentBankConfig":
        for name, value in (("resolution", self.resolution), ("start_resolution", self.start_resolution)):
            least = SWD_MIN_RESOLUTION if name == "resolution" else 4
            if not (_is_power_of_two(value) and value >= least):
                why = f" (pretraining's SWD needs {SWD_MIN_RESOLUTION} px)" if name == "resolution" else ""
                raise _field_error(name, f"a power of two >= {least}{why}", value)
        return self


# ----------------------------------------------------------------------------------------------- model
class ModelConfig(Section):
    latent_bank: bool = setting(True, "ablation: false gives the same DepthNet without the bank")
    pose_vae: bool = setting(True, "ablation: false gives a deterministic PoseNet")
    min_depth: Number = setting(0.1, "smallest depth DepthNet predicts", unit="cm", gt=0)
    max_depth: Number = setting(20.0, "largest depth DepthNet predicts", unit="cm")
    encoder_weights: Optional[str] = setting(None, "optional local ResNet-18 ImageNet state dict")
    # DepthNet's decoder has five levels; disparities come from the four finest (Monodepth2's scales).
    scales: int = setting(4, "decoder scales the loss sees", ge=1, le=4)
    bank_noise: bool = setting(False, "the frozen bank injects its learned per-pixel noise while training (never "
                                      "at evaluation)")
    # std exp(-4.5) ~ 0.011 rad / cm: small, so early samples do not swamp the warp; the KL term then pulls it up
    # against the reprojection loss.
    pose_logvar_init: Number = setting(-9.0, "initial log-variance of the pose VAE")
    pose_sample: bool = setting(True, "with pose_vae, training warps with the reparameterised sample (true, the "
                                      "paper) or the mean (false; the KL still applies); evaluation uses the mean")


class LossConfig(Section):
    photometric: Literal["mse", "ssim_l1"] = setting("ssim_l1", "photometric error")
    ssim_weight: Number = setting(0.85, "SSIM's share of ssim_l1", ge=0, le=1)
    min_reprojection: bool = setting(True, "per-pixel minimum over source frames (Monodepth2)")
    automask: bool = setting(True, "mask pixels the identity warp explains better (Monodepth2)")
    # The mask silences the pose exactly where its answer is wrong: a forward step for a pause or a withdrawal warps
    # worse than no motion, the unwarped neighbour wins, and the pose gets no gradient (docs/results.md).
    automask_pose: bool = setting(True, "with automask, the mask also withholds the pose's gradient (Monodepth2); "
                                        "false: the depth keeps the mask and the pose learns from every pixel's "
                                        "reprojection error (each warp made twice)")
    # The lumen's far end barely moves between frames, so the unwarped neighbour explains it and the mask drops it
    # from the depth's loss; trained so, the far depth comes out compressed (docs/results.md).
    automask_depth: bool = setting(True, "with automask, the mask also withholds the depth's (and a learned K's) "
                                         "gradient (Monodepth2); false: the pose keeps the mask and the depth learns "
                                         "from every pixel's reprojection error (each warp made twice)")
    # Without the mask, the pose VAE's spread learns from every pixel too; the sampling noise is what holds the depth
    # at the metric scale (docs/method.md, "What the VAE contributes").
    automask_pose_spread: bool = setting(False, "with automask_pose false, the pose's sampling spread (the VAE's "
                                                "variance head) still learns from the masked loss and only its mean "
                                                "head from every pixel (their shared encoder from both)")
    # Between consecutive 64-px frames SSIM pulls the translation towards none: with exact depth, SSIM + L1's optimum
    # is 0.73 of the true translation, L1's 0.94 (benchmarks/bench_pose_alignment.py; docs/results.md).
    pose_ssim_weight: Optional[Number] = setting(None, "with automask_pose false, SSIM's share of ssim_l1 in the "
                                                       "pose's own (unmasked) loss; null: ssim_weight", ge=0, le=1)
    smoothness_weight: Number = setting(1e-3, "edge-aware disparity smoothness weight", ge=0)
    multiscale: bool = setting(True, "the loss at every decoder scale, upsampled to full resolution")
    # The paper gives no value; 1e-3 pushed the pose log-variance up until sampling noise (~0.03 rad) swamped the
    # per-frame rotation of the default data, and pose learned nothing (docs/method.md).
    kl_weight: Number = setting(1e-5, "beta, the pose VAE's KL weight", ge=0)
    geometry_weight: Number = setting(
        0.0, "weight of the depth consistency between neighbouring frames (SC-SfMLearner: one scale for depth and "
             "path over a video); 0: off, and no depth pass over the neighbours", ge=0)

    @model_validator(mode="after")
    def _one_part_unmasked(self) -> "LossConfig":
        # both unmasked would train as automask: false while the logged loss stays the masked one's
        if not (self.automask_pose or self.automask_depth):
            raise _field_error("automask_depth", "true while automask_pose is false (for neither part masked: "
                               "loss.automask false)", self.automask_depth)
        return self


# -------------------------------------------------------------------------------------------- training
class TrainConfig(Section):
    shards: str = setting("data/shards/simcol", "training shards (their manifest is in the fingerprint)",
                          training=False)
    # Real unlabelled video beside the built-in data: `-S 'train.mix={data/shards/video: 1.0}'` trains half of every
    # batch on it. Its validation has no depth; the val splits with depth still select the best epoch.
    mix: dict[str, Annotated[Number, Field(gt=0)]] = setting(
        default_factory=dict, doc="more shard folders to train on, each with its weight beside shards' 1: every "
                                  "batch takes samples from each folder in proportion; their val splits validate too "
                                  "(their manifests are in the fingerprint)")
    latent_bank: str = setting("models/latent_bank.pt", "the bank file (its bytes are in the fingerprint)",
                               training=False)
    out: str = setting("models/endoflow.pt", "the model file", training=False)
    metrics: str = setting("metrics/train.json", "what DVC shows of training", training=False)
    plots: str = setting("plots/train", "curves and history", training=False)
    # not in the fingerprint: a run given more epochs resumes from where it stopped
    epochs: Count = setting(10, "training epochs", training=False)
    batch_size: Count = setting(12, "samples per step per worker")
    lr: Number = setting(2e-4, "learning rate", gt=0)
    time_reversal: Number = setting(0.0, "share of training triplets played backwards (prev and next swapped), so "
                                         "that a pose network cannot answer one forward step for every pair",
                                    ge=0, le=1)
    weight_decay: Number = setting(1e-3, "weight decay", ge=0)
    # An assumed focal length can be off by a factor of two: at train.lr the corrections would move too slowly.
    intrinsics_lr: Number = setting(2e-3, "learning rate of the intrinsics learned for cameras whose K is unknown "
                                          "(models/intrinsics.py)", gt=0)
    intrinsics_principal_point: bool = setting(True, "learn the principal point of a camera whose K is unknown beside "
                                                     "its focal lengths; false: held at the assumed centre (forward "
                                                     "motion confounds it with the direction of travel)")
    # adam adds the decay to the gradient (L2), which Adam's normalisation inflates wherever the photometric
    # gradient is small; on the default data it stalls learning.
    optimizer: Literal["adam", "adamw"] = setting("adamw", "adamw: decoupled weight decay; adam: L2 decay")
    log_every: Count = setting(10, "steps between logged training losses", training=False)
    schedule: Literal["constant", "step", "cosine"] = setting(
        "cosine", "learning-rate schedule: constant, step (x gamma every step_epochs, Monodepth2's) or cosine")
    step_epochs: Count = setting(15, "epochs between steps of the step schedule")
    gamma: Number = setting(0.1, "the step schedule's factor", gt=0, le=1)
    grad_clip: Optional[Number] = setting(None, "max gradient norm; null: no clipping", gt=0)
    steps_per_epoch: Optional[Count] = setting(None, "cap per epoch (smoke runs); null: one pass over the shards")
    val_batches: Optional[Count] = setting(None, "cap on validation batches per epoch; null: the whole val split")
    precision: Precision = setting("auto", "auto: bf16 autocast (and channels-last) on a GPU with native bf16, "
                                           "float32 elsewhere; bf16 also runs on the CPU (endoflow.devices)")
    # compiled code rounds differently from eager (a few 1e-6 of a loss), so the setting is part of the run
    compile: Compile = setting("auto", "torch.compile the training step (losses and networks): auto on a GPU, not "
                                       "on a CPU, whose compiler warm-up outlasts a short run; true, false "
                                       "(endoflow.devices)")
    image_examples: int = setting(3, "fixed val frames whose depth is logged beside GT each epoch", ge=0,
                                  training=False)
    # each holds the best epoch's weights too, so the model is never lost; Ray refuses to keep none
    keep_checkpoints: Count = setting(2, "Ray checkpoints kept (the newest)", training=False)
    # The batch order depends on it (0 and 1 agree), so a run resumes only with its value.
    loader_workers: int = setting(0, "processes per Ray worker that read, check, decode and collate its batches "
                                     "(0: the training process does, between steps)", ge=0)


class RayConfig(Section):
    # where training runs, not what it computes (the worker count aside)
    TRAINING: ClassVar[Optional[bool]] = False

    address: Optional[str] = setting(None, "null: local Ray sized for this machine; auto: join a cluster")
    num_workers: Count = setting(1, "training workers (DDP ranks)", training=True)
    use_gpu: bool = setting(False, "one GPU per worker")
    cpus_per_worker: Number = setting(2.0, "CPUs Ray reserves per worker (its loader processes included)", gt=0)
    placement_strategy: Literal["PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD"] = setting(
        "PACK", "PACK / SPREAD as few / as many nodes as it can, STRICT_PACK all on one node, STRICT_SPREAD each "
                "on a node of its own (Ray Train's ScalingConfig.placement_strategy)")
    # A real error is raised after max_failures retries, each repeating at most the epoch it broke in.
    max_failures: int = setting(2, "worker failures Ray Train recovers from by restarting every worker from the "
                                   "newest checkpoint; -1: no limit", ge=-1)
    storage_path: str = setting("ray_results", "checkpoints: a local path (made absolute), a shared filesystem or "
                                               "an fsspec URL")
    num_cpus: Optional[Count] = setting(None, "local Ray only: logical CPUs (null: this machine's)")
    object_store_mb: int = setting(256, "local Ray only: object store size", unit="MB",
                                   ge=RAY_MIN_OBJECT_STORE_MB)
    run_name: str = setting("endoflow-train", "+ a fingerprint of params and data: same inputs resume the run")


# ------------------------------------------------------------------------------------------ evaluation
class EvalSetConfig(Section):
    """One test set: samples of ``split`` in ``<eval.shards>/<dataset>`` whose group/sequence match."""

    dataset: str = setting(doc="the dataset's name (a section of data)")
    groups: list[str] = setting([], "groups it takes; empty: any")
    sequences: list[str] = setting([], "sequences it takes; empty: any")
    split: Split = setting("test", "the split it takes")


def _default_test_sets() -> dict[str, EvalSetConfig]:
    return {
        "simcol_12": EvalSetConfig(dataset="simcol", groups=["SyntheticColon_I", "SyntheticColon_II"]),
        "simcol_3": EvalSetConfig(dataset="simcol", groups=["SyntheticColon_III"]),
        "endoslam_colon": EvalSetConfig(dataset="endoslam", groups=["Colon"]),
        "endoslam_small_intestine": EvalSetConfig(dataset="endoslam", groups=["Small Intestine"]),
    }


class EvalConfig(Section):
    TRAINING: ClassVar[Optional[bool]] = False

    model: str = setting("models/endoflow.pt", "the model evaluated (a path or a models:/ URI)")
    shards: str = setting("data/shards", "holds <dataset>/ shard folders; a local path or an fsspec URL")
    metrics: str = setting("metrics/eval", "<metrics>/<testset>.json")
    plots: str = setting("plots/eval", "<plots>/<testset>/")
    predictions: str = setting("predictions", "<predictions>/<testset>/ in the SimCol3D challenge layout")
    test_sets: dict[str, EvalSetConfig] = setting(
        default_factory=_default_test_sets, doc="by name (an evaluate@<name> stage each): samples of split in "
        "<shards>/<dataset> whose group and sequence are listed (an empty list takes any)")
    batch_size: Count = setting(8, "frames per forward pass")
    depth_examples: int = setting(3, "frames shown with error maps per test set", ge=0)
    max_frames_per_sequence: Optional[Count] = setting(None, "null: every frame")
    device: Device = setting("auto", "auto, cpu, cuda or cuda:N (endoflow.devices)")
    precision: Precision = setting("auto", "as train.precision; depth and pose are scored in float32")


# -------------------------------------------------------------------------------------- reconstruction
class ReconstructSequenceConfig(Section):
    """One sequence the ``reconstruct`` stage reconstructs and measures: ``sequence`` of ``data.<dataset>.root``
    (a name its reader lists), frames ``start, start + stride, ...`` below ``stop`` (null: to the end)."""

    dataset: str = setting(doc="the dataset's name (a section of data with images)")
    sequence: str = setting(doc="a sequence its reader lists")
    start: int = setting(0, "first frame", ge=0)
    stop: Optional[int] = setting(None, "frames below this; null: to the end")
    stride: Count = setting(1, "every stride-th frame")

    @model_validator(mode="after")
    def _stop_after_start(self) -> "ReconstructSequenceConfig":
        if self.stop is not None and self.stop <= self.start:
            raise _field_error("stop", f"above start ({self.start}) or null", self.stop)
        return self


def _default_reconstructions() -> dict[str, ReconstructSequenceConfig]:
    return {
        "simcol_S5": ReconstructSequenceConfig(dataset="simcol", sequence="S5"),
        "simcol_O1": ReconstructSequenceConfig(dataset="simcol", sequence="O1"),
        "endoslam_colon": ReconstructSequenceConfig(dataset="endoslam", sequence="UnityCam/Colon"),
    }


class ReconstructConfig(Section):
    TRAINING: ClassVar[Optional[bool]] = False

    model: str = setting("models/endoflow.pt", "the model (a path or a models:/ URI)")
    out: str = setting("reconstructions", "<out>/<name>/: what `endoflow reconstruct` writes")
    metrics: str = setting("metrics/reconstruct", "<metrics>/<name>.json: path and surface errors against ground "
                                                  "truth")
    plots: str = setting("plots/reconstruct", "<plots>/<name>/: the picture sheet and per-frame path errors")
    sequences: dict[str, ReconstructSequenceConfig] = setting(
        default_factory=_default_reconstructions, doc="by name (a reconstruct@<name> stage each): frames start, "
        "start + stride, ... below stop (null: to the end) of a sequence of data.<dataset>.root")
    size: Optional[ImageSize] = setting(None, "null: the model's data.size", unit="px")
    voxel_cm: Optional[Number] = setting(
        None, "in the model's depth unit; null: about one pixel's footprint at the first frame's far depth (its 95th "
        "percentile)", unit="cm", gt=0)
    trunc_cm: Optional[Number] = setting(None, "null: 4 voxels", unit="cm", gt=0)
    device: Device = setting("auto", "auto, cpu, cuda or cuda:N (endoflow.devices)")
    # self-supervised, the sequence's ground truth unused: what `endoflow reconstruct --adapt` does for a user's video
    adapt: int = setting(0, "first fit the model to the sequence with `endoflow adapt` for this many steps; where "
                            "the fit explains its held-out frames better it reconstructs, and is written beside the "
                            "reconstruction; 0: the model as trained", unit="steps", ge=0)
    # bf16 rounds depth and pose a little differently (docs/reconstruction.md, "Precision", measures what it costs)
    precision: Precision = setting("float32", "the networks' arithmetic: float32 (the same outputs on any machine), "
                                              "bf16 autocast (faster where the CPU or GPU has bf16 arithmetic) or "
                                              "auto as for train.precision")


# ---------------------------------------------------------------------------------------------- refine
class RefineConfig(Section):
    """The pose network's path refined by direct photometric alignment of each frame to a keyframe with the
    predicted depth (endoflow/geometry/direct_alignment.py): what `reconstruct` writes, and a method of its own
    beside the pose network's in `evaluate`."""

    TRAINING: ClassVar[Optional[bool]] = False

    enabled: bool = setting(True, "refine the path (false: the pose network's chain as it is)")
    levels: Count = setting(3, "image pyramid levels, coarse to fine")
    # null: with a trained model at 480 px, 240 made the whole reconstruct call 1.51x faster and the refined path's
    # rotation error 0.089 instead of 0.071 deg a frame (benchmarks/bench_refine_size.py; docs/benchmarks.md)
    max_size: Optional[Count] = setting(None, "the finest level's longer side at most this: larger frames are "
                                              "halved until they fit; null: full resolution", unit="px")
    iterations: Count = setting(12, "Gauss-Newton steps per level at most")
    huber: Number = setting(0.04, "residual beyond which a pixel counts less (intensity in [0, 1])", gt=0)
    # 0.91 (an inverse-square fall-off through display gamma 2.2) is right with exact depth; with the model's depth
    # the fall-off model added error: 0 gave ROT 0.120 against 0.153 deg (base model, S5, B5, S10; docs/results.md)
    light_falloff: Number = setting(0.0, "the light sits at the lens: model brightness as distance^-this; 0: no "
                                         "fall-off", ge=0)
    # chosen on the SimCol3D validation sequences (0, 0.1, 0.3, 1, 3): the refined path's RTE 0.0100, 0.0086, 0.0094,
    # 0.0129, 0.0157 cm and ROT 0.172, 0.155, 0.165, 0.229, 0.291 deg (base model seed 0; docs/results.md)
    rotation_prior: Number = setting(0.1, "pull of each refined step's rotation towards the pose network's step: "
                                          "a cost of rotation_prior / 2 * (angle between them)^2 per pixel, "
                                          "angle in radians; 0: the rotation is free", ge=0)
    # chosen on the SimCol3D validation sequences at rotation_prior 0.1 (docs/results.md, "The refined path's
    # rotation smoothed": benchmarks/bench_rotation_smoothing.py --split val)
    rotation_smoothing: Number = setting(3.0, "the refined path's orientations smoothed, its positions kept: the "
                                              "standard deviation of the Gaussian window of a local straight-line "
                                              "fit over the frames around each, reaching ceil(3 x this) frames "
                                              "either way (9 at 3; reconstruct fuses and writes that many frames "
                                              "behind the tracker); 0: the orientations as aligned",
                                         unit="frames", ge=0)
    keyframe_every: Count = setting(6, "a new keyframe after this many frames at most", unit="frames")
    min_overlap: Number = setting(0.5, "... or once a smaller share of the keyframe's pixels still takes part",
                                  ge=0, le=1)
    # off: with the model's depth the chained factors drift while the camera advances (to 0.59 over SimCol O1), though
    # they take the real C3VD sample's drift from 1.56 to 1.09 (seed 0; docs/results.md, "The depth rescaled to its
    # keyframes")
    depth_scale: bool = setting(False, "each frame's depth rescaled, once the frame is aligned, to agree with its "
                                       "keyframe's seen from there, chained from the first frame: the depth and "
                                       "the path in one scale along the sequence (reconstruct fuses and writes "
                                       "the rescaled depth)")


# -------------------------------------------------------------------------------------------- tracking
class TrackingConfig(Section):
    TRAINING: ClassVar[Optional[bool]] = False

    uri: Optional[str] = setting(None, "null: embedded SQLite store at <project>/mlflow.db with artifacts in "
                                       "<project>/mlartifacts")
    experiment: str = setting("endoflow", "training and evaluation runs")
    latent_bank_experiment: str = setting("endoflow-latent-bank", "pretraining runs")
    # MLflow's registry takes other characters too, but a models:/<name>/<version> URI must parse back
    registered_model: Optional[PlainName] = setting(
        None, "a name: each training registers its model as a new version of it (models:/<name>/<version>, which "
              "`endoflow reconstruct --model` and eval.model accept); null: not registered")


# ------------------------------------------------------------------------------------------------- all
class Params(Section):
    TRAINING: ClassVar[Optional[bool]] = True

    seed: int = setting(0, "the seed every random generator of pretraining and training starts from", ge=0)
    # float sums split over threads add in another order, so the same seed gives other numbers with another
    # count; a fixed count, not the machine's cores, makes them the same on any machine
    threads: Count = setting(2, "torch's CPU threads in every process that computes")
    data: DataConfig = setting(default_factory=DataConfig)
    synth: SynthConfig = setting(default_factory=SynthConfig)
    preprocess: PreprocessConfig = setting(default_factory=PreprocessConfig)
    latent_bank: LatentBankConfig = setting(default_factory=LatentBankConfig)
    model: ModelConfig = setting(default_factory=ModelConfig)
    loss: LossConfig = setting(default_factory=LossConfig)
    train: TrainConfig = setting(default_factory=TrainConfig)
    ray: RayConfig = setting(default_factory=RayConfig)
    tracking: TrackingConfig = setting(default_factory=TrackingConfig)
    eval: EvalConfig = setting(default_factory=EvalConfig)
    reconstruct: ReconstructConfig = setting(default_factory=ReconstructConfig)
    refine: RefineConfig = setting(default_factory=RefineConfig)

    @model_validator(mode="after")
    def _cross_field_rules(self) -> "Params":
        for rule in _CROSS_FIELD_RULES:
            problem = rule(self)
            if problem:
                raise PydanticCustomError("cross_field", "{problem}", {"problem": problem})
        return self


# The datasets endoflow reads, one per section of ``data``: the one list every command, stage, reader and
# writer takes. SceneNet is read for its depth alone (the latent bank): its shards hold no triplets.
DATASETS = tuple(name for name, info in DataConfig.model_fields.items()
                 if isinstance(info.annotation, type) and issubclass(info.annotation, Section))
DEPTH_ONLY_DATASETS = frozenset({"scenenet"})
# The layouts the built-in renderer writes (`endoflow synth`, stage `synthesize`), one per section of ``synth``.
SYNTH_LAYOUTS = ("simcol", "endoslam", "scenenet", "video")


# ---------------------------------------------------------------------------------------- cross-field rules
def _depth_range(p: Params) -> Optional[str]:
    if p.model.min_depth >= p.model.max_depth:
        return f"model.min_depth ({p.model.min_depth}) must be below model.max_depth ({p.model.max_depth})"
    return None


def _encoder_batch_norm(p: Params) -> Optional[str]:
    # At the smallest size the encoder's last features are 1x1, and BatchNorm in training mode needs more than
    # one value per channel: a batch of one fails at the first step.
    if p.data.size == ENCODER_STRIDE and p.train.batch_size < 2:
        return (f"train.batch_size must be >= 2 when data.size is {ENCODER_STRIDE} (the encoder's 1x1 features give "
                f"BatchNorm one value per channel), got {p.train.batch_size}")
    return None


def bank_resolutions(cfg: LatentBankConfig) -> list[int]:
    """The generator's block resolutions, ``start_resolution`` doubling up to ``resolution``."""
    resolutions = [cfg.start_resolution]
    while resolutions[-1] < cfg.resolution:
        resolutions.append(resolutions[-1] * 2)
    return resolutions


def _bank_growth(p: Params) -> Optional[str]:
    cfg = p.latent_bank
    if cfg.start_resolution > cfg.resolution:
        return (f"latent_bank.start_resolution ({cfg.start_resolution}) must not exceed latent_bank.resolution "
                f"({cfg.resolution})")
    resolutions = bank_resolutions(cfg)
    for name in ("steps_per_stage", "n_critic"):
        value = getattr(cfg, name)
        if isinstance(value, list) and len(value) != len(resolutions):
            return (f"latent_bank.{name} must be one number or a list of {len(resolutions)} (one per resolution "
                    f"{resolutions}), got {value}")
    return None


def _synth_triplets(p: Params) -> Optional[str]:
    offset = max([p.preprocess.neighbour_offset, *(p.preprocess.train_offsets or [])])
    for layout in (name for name in SYNTH_LAYOUTS if name not in DEPTH_ONLY_DATASETS):
        for key in ("frames", "test_frames"):
            frames = getattr(getattr(p.synth, layout), key, None)
            if frames is not None and frames <= 2 * offset:
                return (f"synth.{layout}.{key} must exceed 2 x the largest of preprocess.neighbour_offset and "
                        f"train_offsets = {2 * offset} (a sample needs frames cur - {offset} and cur + {offset}), "
                        f"got {frames}")
    return None


def _ray_fits_local_cpus(p: Params) -> Optional[str]:
    ray = p.ray
    if ray.address or ray.num_cpus is None:  # connect_ray starts a local Ray for an empty address too
        return None
    need = ray.num_workers * ray.cpus_per_worker
    if need > ray.num_cpus:
        return (f"ray.num_workers x ray.cpus_per_worker = {ray.num_workers} x {ray.cpus_per_worker:g} = {need:g} "
                f"CPUs exceed ray.num_cpus = {ray.num_cpus} of the local Ray (ray.address null); Ray would wait "
                f"forever")
    return None


def _workers_have_shards(p: Params) -> Optional[str]:
    # Otherwise a worker finds no shard of its own (loader.rank_shards) once training or validation starts.
    if p.ray.num_workers > p.preprocess.shard_multiple:
        multiple = p.preprocess.shard_multiple
        return (f"ray.num_workers ({p.ray.num_workers}) must not exceed preprocess.shard_multiple ({multiple}): a "
                f"split has a multiple of {multiple} shards, maybe just {multiple}, and every worker needs a shard "
                f"of its own")
    return None


def _loader_workers_fit_worker_cpus(p: Params) -> Optional[str]:
    # Loader processes run beside the training process inside the CPUs Ray reserves for the worker; beyond them
    # they would take cores from other workers or trials on the node.
    loaders, cpus = p.train.loader_workers, p.ray.cpus_per_worker
    if loaders and loaders + 1 > cpus:
        return (f"train.loader_workers ({loaders}) + 1 (the training process) = {loaders + 1} CPUs exceed "
                f"ray.cpus_per_worker = {cpus:g}; raise ray.cpus_per_worker or lower train.loader_workers")
    return None


def _named_entries(p: Params) -> Optional[str]:
    # Test-set and sequence names name DVC stages, folders and dotted keys.
    with_images = [name for name in DATASETS if name not in DEPTH_ONLY_DATASETS]
    for section, entries, datasets in (("eval.test_sets", p.eval.test_sets, list(DATASETS)),
                                       ("reconstruct.sequences", p.reconstruct.sequences, with_images)):
        for name, entry in entries.items():
            if not _is_plain_name(name):
                return f"{section}: name {name!r} must be letters, digits, _ and - only (it names a DVC stage)"
            if entry.dataset not in datasets:
                return f"{section}.{name}.dataset must be one of {datasets}, got {entry.dataset!r}"
    return None


_CROSS_FIELD_RULES: tuple[Callable[[Params], Optional[str]], ...] = (
    _depth_range, _encoder_batch_norm, _bank_growth, _synth_triplets, _ray_fits_local_cpus, _workers_have_shards,
    _loader_workers_fit_worker_cpus, _named_entries,
)


# --------------------------------------------------------------------------------------------- loading
def load_params(path: str | Path = "params.yaml", overrides: Sequence[str] = ()) -> Params:
    """Read ``path`` (keys left out take the schema's defaults) and apply ``key=value`` overrides (values parsed
    as YAML), then validate.

    Raises:
        ConfigError: naming the file and the dotted key that is unknown, mistyped or out of range.
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
    """Validate a plain mapping (as parsed from YAML) into :class:`Params`: types, ranges, cross-field rules.

    Keys left out take the schema's defaults, within sections too (``synth.endoslam: {frames: 10}`` keeps the
    default sequence count); a mapping of named entries (``eval.test_sets``) given is taken whole.
    """
    try:
        return Params.model_validate(_over_defaults(raw, Params().model_dump(), Params))
    except ValidationError as exc:
        raise ConfigError("; ".join(_describe(error) for error in exc.errors())) from None


def _over_defaults(raw: dict[str, Any], defaults: dict[str, Any], section: type[Section]) -> dict[str, Any]:
    """``raw`` with every key it leaves out of ``section`` (and of the sections within it) taken from ``defaults``."""
    merged = dict(raw)
    for name, info in section.model_fields.items():
        inner = info.annotation
        if isinstance(inner, type) and issubclass(inner, Section) and isinstance(raw.get(name), dict):
            merged[name] = _over_defaults(raw[name], defaults[name], inner)
        else:
            merged.setdefault(name, defaults[name])
    return merged


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

    Reaches into nested sections and mappings of sections (such as ``eval.test_sets``); used for MLflow params
    and for the training fingerprint.
    """
    tree = params.model_dump() if isinstance(params, BaseModel) else params
    flat: dict[str, Any] = {}
    for name, value in tree.items():
        key = f"{prefix}{name}"
        if isinstance(value, dict) and value:  # an empty mapping (train.mix) stays a key
            flat.update(flatten_params(value, prefix=f"{key}."))
        else:
            flat[key] = value
    return flat


def params_to_dict(params: BaseModel) -> dict[str, Any]:
    """Nested plain-dict form, for writing back to YAML or JSON."""
    return params.model_dump()


def training_keys(params: Params) -> list[str]:
    """The flat keys (as :func:`flatten_params` names them) of the fields that change what training computes; a
    mapping of values (``train.mix``) is one key, its entries' flat keys below it."""
    return sorted(_training_keys(params, "", inherited=True))


def _training_keys(section: Section, prefix: str, inherited: bool) -> set[str]:
    own = type(section).TRAINING
    default = inherited if own is None else own
    keys: set[str] = set()
    for name, info in type(section).model_fields.items():
        marked = (info.json_schema_extra or {}).get("training")
        changes_training = default if marked is None else marked
        value = getattr(section, name)
        entries = value.items() if isinstance(value, dict) else [(None, value)]
        if all(isinstance(item, Section) for _, item in entries) and value:
            for entry, item in entries:
                keys |= _training_keys(item, f"{prefix}{name}." + (f"{entry}." if entry else ""), changes_training)
        elif changes_training:
            keys.add(f"{prefix}{name}")
    return keys


# ------------------------------------------------------------------------------------- error messages
def _field_error(key: str, expected: str, value: Any) -> PydanticCustomError:
    """An error a model validator raises for one of its fields, read as ``<key> must be <expected>, got <value>``."""
    return PydanticCustomError("field", "{key} must be {expected}, got {value}",
                               {"key": key, "expected": expected, "value": repr(value)})


_WORDS = {
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
    "float_type": "a number", "float_parsing": "a number", "finite_number": "a finite number",
    "bool_type": "true or false", "string_type": "a string", "list_type": "a list",
    "dict_type": "a mapping", "model_type": "a mapping",
}
_BOUNDS = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def section_path(cls: type[Section]) -> str:
    """Where a section class sits in :class:`Params` (``train``, ``data.simcol``, ``eval.test_sets.*``); its class
    name where it does not."""
    def find(section: type[BaseModel], prefix: str) -> Optional[str]:
        for name, info in section.model_fields.items():
            child = _section_after(section, name)
            entry = child.cls if isinstance(child, _Entries) else child
            if entry is None:
                continue
            path = f"{prefix}{name}" + (".*" if isinstance(child, _Entries) else "")
            if entry is cls:
                return path
            found = find(entry, path + ".")
            if found:
                return found
        return None

    return "" if cls is Params else find(Params, "") or cls.__name__


def _describe(error: dict[str, Any], root: type[Section] = Params, where: str = "") -> str:
    """``<dotted key> must be <expected>, got <value>`` for one pydantic error (keys from ``root`` down, under
    ``where``, the root's own path)."""
    key = ".".join(part for part in (where, _dotted(error["loc"], root)) if part)
    kind, ctx, value = error["type"], error.get("ctx") or {}, error.get("input")
    if kind == "extra_forbidden":
        return _unknown_key(error["loc"], root)
    if kind == "missing":
        return f"missing key {key}"
    if kind in ("cross_field", "field"):
        return f"{key}.{error['msg']}" if kind == "field" and key else error["msg"]
    if kind == "literal_error":
        return f"{key} must be one of {_literal_choices(error['loc'], root)}, got {value!r}"
    if kind in _BOUNDS:
        bound = next(iter(ctx.values()))
        return f"{key} must be {_BOUNDS[kind]} {bound:g}, got {value!r}"
    if kind == "too_short":
        least = ctx.get("min_length")
        return f"{key} must be a list of at least {least} entr{'y' if least == 1 else 'ies'}, got {value!r}"
    if kind == "too_long":
        return f"{key} must be a list of at most {ctx.get('max_length')} entries, got {value!r}"
    if kind == "expected":
        return f"{key} must be {ctx['expected']}, got {value!r}"
    if kind == "entry":
        return f"{key}[{ctx['index']}] must be {ctx['expected']}, got {ctx['value']}"
    expected = _WORDS.get(kind, error["msg"].removeprefix("Input should be "))
    return f"{key} must be {expected}, got {value!r}"


def _dotted(loc: tuple, root: type[Section]) -> str:
    """``("data", "simcol", "intrinsics", 0, 1)`` as ``data.simcol.intrinsics[0][1]``; union branch tags left out."""
    text = ""
    for part in _plain_loc(loc, root):
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


def _plain_loc(loc: tuple, root: type[Section]) -> list:
    """``loc`` without pydantic's union branch names (``int``, ``list[constrained-int]``), which follow a leaf."""
    parts: list = []
    section: Any = root
    for part in loc:
        if section is None and not isinstance(part, int):
            continue
        parts.append(part)
        section = _section_after(section, part)
    return parts


def _section_after(section: Any, part: Any) -> Any:
    """The section class a loc part leads to, or None past the sections."""
    if isinstance(section, _Entries):
        return section.cls
    if not (isinstance(section, type) and issubclass(section, BaseModel)) or part not in section.model_fields:
        return None
    annotation = section.model_fields[part].annotation
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    args = getattr(annotation, "__args__", ())
    if (getattr(annotation, "__origin__", None) is dict and len(args) == 2 and isinstance(args[1], type)
            and issubclass(args[1], BaseModel)):
        return _Entries(args[1])
    return None


class _Entries:
    """A mapping of named sections (``eval.test_sets``): its keys are names, its values ``cls``."""

    def __init__(self, cls: type) -> None:
        self.cls = cls


def _unknown_key(loc: tuple, root: type[Section]) -> str:
    parts = _plain_loc(loc, root)
    section: Any = root
    for part in parts[:-1]:
        section = _section_after(section, part)
    known = sorted(section.model_fields) if isinstance(section, type) else []
    close = difflib.get_close_matches(str(parts[-1]), known, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown key {_dotted(loc, root)} (known: {', '.join(known)}){hint}"


def _literal_choices(loc: tuple, root: type[Section]) -> list:
    parts = _plain_loc(loc, root)
    section: Any = root
    for part in parts[:-1]:
        section = _section_after(section, part)
    annotation = section.model_fields[parts[-1]].annotation
    return list(getattr(annotation, "__args__", ()))
