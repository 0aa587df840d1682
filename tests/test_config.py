"""params.yaml is validated once, and every mistake names its key."""

import re
from pathlib import Path

import pytest
import yaml

from endoflow.config import (
    ConfigError,
    Params,
    apply_override,
    flatten_params,
    load_params,
    params_from_dict,
    params_to_dict,
    training_keys,
)
from endoflow.cli import main
from endoflow.params_file import write_params_file

PROJECT = Path(__file__).resolve().parents[1]


def write_params(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


PRESETS = sorted((PROJECT / "presets").glob("*.yaml"))


def test_params_yaml_is_the_schema_defaults():
    # One source for every default: the committed params.yaml (what DVC reads) is what the schema says, so an
    # empty params file means exactly params.yaml. `endoflow params --out params.yaml` rewrites it.
    assert yaml.safe_load((PROJECT / "params.yaml").read_text()) == params_to_dict(Params())
    assert load_params(PROJECT / "params.yaml") == Params()


def test_params_yaml_is_what_the_params_command_writes(tmp_path, capsys):
    # its comments (what each key means, its unit) come from the schema too
    assert main(["params"]) == 0
    assert capsys.readouterr().out == (PROJECT / "params.yaml").read_text(), \
        "params.yaml is stale: run `endoflow params --out params.yaml`"
    assert main(["params", "--preset", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml: parameter file not found" in capsys.readouterr().err


def test_empty_params_file_means_params_yaml(tmp_path):
    empty = tmp_path / "params.yaml"
    empty.write_text("")
    assert load_params(empty) == load_params(PROJECT / "params.yaml")


def test_written_params_file_documents_every_key_and_reads_back(tmp_path):
    out = tmp_path / "params.yaml"
    for preset in [None, *PRESETS]:
        params = write_params_file(out, preset)
        text = out.read_text()
        assert load_params(out) == params
        assert yaml.safe_load(text) == params_to_dict(params)
        # a key is documented on the line above it (`# ...`), except inside named entries (test sets, sequences)
        assert text.count("\n  # ") > 100


# Mappings of named entries: a preset that gives one gives it whole (its entries are all there is), so it is the
# mapping that must differ from the default's, not each value of its entries.
NAMED_ENTRIES = (("eval", "test_sets"), ("reconstruct", "sequences"))


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: p.name)
def test_presets_state_only_their_differences(path):
    raw = yaml.safe_load(path.read_text())
    params, defaults_tree = load_params(path), Params()
    for section, field in NAMED_ENTRIES:
        if field in (raw.get(section) or {}):
            given = getattr(getattr(params, section), field)
            assert given != getattr(getattr(defaults_tree, section), field), (
                f"{path.name}: {section}.{field} repeats the default")
            del raw[section][field]
            if not raw[section]:
                del raw[section]
    overlay = flatten_params(raw)
    defaults = flatten_params(defaults_tree)
    assert overlay, f"{path.name} is empty"
    for key, value in overlay.items():
        if key.rpartition(".")[0] in defaults and isinstance(defaults[key.rpartition(".")[0]], dict):
            continue  # an entry of a mapping the defaults leave empty (train.mix)
        assert key in defaults, f"{path.name}: {key} is no key of the schema"
        assert value != defaults[key], f"{path.name}: {key} repeats the default {value!r}"


def test_a_partial_section_keeps_the_other_defaults_of_that_section():
    params = params_from_dict({"synth": {"endoslam": {"frames": 10}}, "train": {"lr": 1e-3}})
    assert params.synth.endoslam.frames == 10
    assert params.synth.endoslam.sequences == Params().synth.endoslam.sequences
    assert params.train.epochs == Params().train.epochs
    # named entries given are taken whole: a preset that lists test sets means exactly those
    only = params_from_dict({"eval": {"test_sets": {"mine": {"dataset": "simcol"}}}})
    assert list(only.eval.test_sets) == ["mine"]


def test_training_keys_are_derived_from_the_schema():
    keys = set(training_keys(Params()))
    flat = flatten_params(Params())
    assert keys <= set(flat)
    # what training computes
    for key in ("seed", "threads", "model.latent_bank", "loss.kl_weight", "loss.geometry_weight", "train.lr",
                "train.batch_size", "train.loader_workers", "ray.num_workers"):
        assert key in keys, key
    # where it runs, how long, what it logs, every later stage, and what reaches training as files whose bytes
    # the fingerprint hashes (the shards, the bank): editing these resumes an interrupted training
    for prefix in ("train.epochs", "train.out", "train.log_every", "ray.use_gpu", "ray.cpus_per_worker",
                   "ray.storage_path", "synth.", "data.", "preprocess.", "latent_bank.", "eval.", "reconstruct.",
                   "tracking."):
        assert not any(key.startswith(prefix) for key in keys), prefix
        assert any(key.startswith(prefix) for key in flat), prefix


def test_round_trip_through_plain_dict():
    params = Params()
    assert params_from_dict(params_to_dict(params)) == params


def test_unknown_key_is_named(tmp_path):
    path = write_params(tmp_path, {"model": {"latent_bnak": True}})
    with pytest.raises(ConfigError, match=r"params\.yaml: unknown key model\.latent_bnak"):
        load_params(path)


def test_wrong_type_is_named(tmp_path):
    path = write_params(tmp_path, {"data": {"size": "big"}})
    with pytest.raises(ConfigError, match=r"data\.size must be an integer, got 'big'"):
        load_params(path)


def test_bool_is_not_an_integer_and_int_is_a_float(tmp_path):
    with pytest.raises(ConfigError, match="data.size"):
        params_from_dict({"data": {"size": True}})
    assert params_from_dict({"train": {"lr": 1}}).train.lr == 1.0


def test_choices_are_enforced():
    with pytest.raises(ConfigError, match=r"loss\.photometric must be one of"):
        params_from_dict({"loss": {"photometric": "l2"}})
    for key in ("train.precision", "latent_bank.precision", "eval.precision"):
        with pytest.raises(ConfigError, match=rf"^{re.escape(key)} must be one of \['auto', 'bf16', 'float32'\], "
                                              rf"got 'fp16'$"):
            params_from_dict(defaults_with({key: "fp16"}))


def test_device_keys_take_auto_cpu_cuda_and_numbered_gpus():
    for name in ("auto", "cpu", "cuda", "cuda:1"):
        params = params_from_dict(defaults_with({"synth.device": name, "latent_bank.device": name,
                                                 "eval.device": name}))
        assert params.synth.device == params.latent_bank.device == params.eval.device == name


def test_nested_list_types_are_checked():
    with pytest.raises(ConfigError, match=r"data\.simcol\.intrinsics\[0\]\[1\] must be a number"):
        params_from_dict({"data": {"simcol": {"intrinsics": [[1, "x", 0], [0, 1, 0], [0, 0, 1]]}}})


def test_overrides_parse_yaml_values(tmp_path):
    path = write_params(tmp_path, {})
    params = load_params(path, overrides=["model.latent_bank=false", "train.lr=3e-4", "ray.address=auto"])
    assert params.model.latent_bank is False
    assert params.train.lr == pytest.approx(3e-4)
    assert params.ray.address == "auto"


def test_malformed_override_is_rejected():
    with pytest.raises(ConfigError, match="expected key=value"):
        apply_override({}, "model.latent_bank")


def test_missing_file_and_bad_yaml_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: [unclosed")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        load_params(bad)


def test_flat_view_uses_dotted_keys():
    flat = flatten_params(Params())
    assert flat["model.latent_bank"] is True
    assert flat["data.simcol.reference_size"] == 475


def test_exponent_without_dot_is_a_number():
    # PyYAML reads `1e-4` as a string; a learning rate written that way must still work.
    assert params_from_dict(yaml.safe_load("train: {lr: 1e-4}")).train.lr == pytest.approx(1e-4)
    with pytest.raises(ConfigError, match=r"train\.lr must be a number, got 'fast'"):
        params_from_dict({"train": {"lr": "fast"}})


# ------------------------------------------------------------------------------------------- ranges
def defaults_with(settings: dict) -> dict:
    """The defaults as a plain mapping, with ``{"train.lr": 1, ...}`` set in it."""
    raw = params_to_dict(Params())
    for key, value in settings.items():
        *sections, name = key.split(".")
        node = raw
        for section in sections:
            node = node[section]
        node[name] = value
    return raw


# (the key the error must name, a bad value); each case is one rule.
OUT_OF_RANGE = [
    ("seed", -1),
    ("data.size", 50),  # not a multiple of the encoder's stride 32
    ("data.size", 0),
    ("data.simcol.reference_size", 0),
    ("data.endoslam.unitycam_translation_to_cm", 0.0),
    ("data.endoslam.camera_translation_to_cm", -100.0),
    ("data.endoslam.depth_full_scale_cm", 0.0),
    ("data.endoslam.fps", 0.0),
    ("data.scenenet.max_frames_per_trajectory", 0),
    ("synth.size", 4),
    ("synth.seed", -1),
    ("synth.workers", 0),
    ("synth.device", "gpu"),
    ("synth.simcol.sequences", 0),
    ("synth.endoslam.sequences", 0),
    ("synth.scenenet.sequences", 0),
    ("synth.scenenet.frames", 1),
    ("preprocess.workers", 0),
    ("preprocess.samples_per_shard", 0),
    ("preprocess.shard_multiple", 0),
    ("preprocess.neighbour_offset", 0),
    ("preprocess.train_offsets", []),
    ("data.simcol.intrinsics", [[1.0, 0.0], [0.0, 1.0]]),
    ("data.endoslam.intrinsics", [[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0]]),
    ("loss.geometry_weight", -0.5),
    ("synth.simcol.test_frames", 1),
    ("latent_bank.resolution", 48),
    ("latent_bank.resolution", 8),  # below the SWD's 16 px
    ("latent_bank.start_resolution", 2),
    ("latent_bank.start_resolution", 12),
    ("latent_bank.latent_dim", 0),
    ("latent_bank.style_dim", 0),
    ("latent_bank.mapping_layers", 0),
    ("latent_bank.channel_base", 0),
    ("latent_bank.channel_max", 0),
    ("latent_bank.batch_size", 0),
    ("latent_bank.steps_per_stage", 0),
    ("latent_bank.lr", 0.0),
    ("latent_bank.betas", [0.0]),
    ("latent_bank.n_critic", 0),
    ("latent_bank.gp_gamma", -1.0),
    ("latent_bank.ema_decay", 1.0),
    ("latent_bank.conv_init_scale", 0.0),
    ("latent_bank.swd_samples", 0),
    ("latent_bank.drift_weight", -0.001),
    ("latent_bank.fade_fraction", 1.5),
    ("latent_bank.depth_log_range", 0.0),
    ("latent_bank.holdout_fraction", 1.0),
    ("latent_bank.device", "cuda:first"),
    ("model.min_depth", 0.0),
    ("model.scales", 0),
    ("model.scales", 5),
    ("loss.ssim_weight", 1.1),
    ("loss.smoothness_weight", -1e-3),
    ("loss.kl_weight", -1e-5),
    ("train.epochs", 0),
    ("train.batch_size", 0),
    ("train.lr", -0.1),
    ("train.weight_decay", -1e-3),
    ("train.log_every", 0),
    ("train.step_epochs", 0),
    ("train.gamma", 0.0),
    ("train.gamma", 1.5),
    ("train.grad_clip", 0.0),
    ("train.steps_per_epoch", 0),
    ("train.val_batches", 0),
    ("train.image_examples", -1),
    ("train.keep_checkpoints", 0),
    ("ray.num_workers", 0),
    ("ray.cpus_per_worker", 0.0),
    ("ray.num_cpus", 0),
    ("ray.object_store_mb", 74),  # Ray's minimum is 75 MiB
    ("eval.batch_size", 0),
    ("eval.depth_examples", -1),
    ("eval.max_frames_per_sequence", 0),
    ("eval.device", "CUDA"),
]


@pytest.mark.parametrize(("key", "value"), OUT_OF_RANGE, ids=lambda x: str(x))
def test_out_of_range_value_names_key_value_and_expectation(key, value):
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)} must be .+, got {re.escape(repr(value))}$"):
        params_from_dict(defaults_with({key: value}))


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("latent_bank.steps_per_stage", [300, 300, 0, 300, 300], "latent_bank.steps_per_stage[2]"),
        ("latent_bank.n_critic", [1, 1, 1, 1, -1], "latent_bank.n_critic[4]"),
        ("latent_bank.betas", [0.0, 1.0], "latent_bank.betas[1]"),
        ("preprocess.train_offsets", [1, 0], "preprocess.train_offsets[1]"),
    ],
)
def test_bad_list_entry_is_named_by_index(key, value, named):
    with pytest.raises(ConfigError, match=rf"^{re.escape(named)} must be"):
        params_from_dict(defaults_with({key: value}))


def test_load_names_file_key_and_value(tmp_path):
    path = write_params(tmp_path, {})
    with pytest.raises(ConfigError, match=r"params\.yaml: train\.lr must be > 0, got -0\.1$"):
        load_params(path, overrides=["train.lr=-0.1"])


def test_boundary_values_are_accepted():
    params = params_from_dict(defaults_with({
        "data.size": 96, "latent_bank.ema_decay": 0.0, "latent_bank.fade_fraction": 1.0, "train.gamma": 1.0,
        "loss.ssim_weight": 0.0, "train.weight_decay": 0.0, "ray.object_store_mb": 75, "eval.depth_examples": 0,
        "latent_bank.steps_per_stage": [1, 2, 3, 4, 5], "latent_bank.n_critic": [5, 4, 3, 2, 1],
    }))
    assert params.latent_bank.steps_per_stage == [1, 2, 3, 4, 5]


def test_defaults_pass_every_rule():
    assert params_from_dict({}) == Params()


# -------------------------------------------------------------------------------------- cross-field
# (settings that contradict each other, the keys the error must name); each case is one rule.
CONTRADICTIONS = [
    ({"model.min_depth": 20.0, "model.max_depth": 20.0}, ["model.min_depth", "model.max_depth"]),
    ({"loss.automask_pose": False, "loss.automask_depth": False},
     ["loss.automask_depth", "automask_pose is false", "loss.automask false"]),
    ({"data.size": 32, "train.batch_size": 1}, ["train.batch_size", "data.size"]),
    ({"latent_bank.start_resolution": 64, "latent_bank.resolution": 32},
     ["latent_bank.start_resolution", "latent_bank.resolution"]),
    ({"latent_bank.steps_per_stage": [300, 300]}, ["latent_bank.steps_per_stage", "[4, 8, 16, 32, 64]"]),
    ({"latent_bank.n_critic": [1, 1, 1, 1, 1, 1]}, ["latent_bank.n_critic", "list of 5"]),
    ({"synth.simcol.frames": 2}, ["synth.simcol.frames", "preprocess.neighbour_offset"]),
    ({"synth.endoslam.frames": 4, "preprocess.neighbour_offset": 2},
     ["synth.endoslam.frames", "preprocess.neighbour_offset and train_offsets = 4"]),
    ({"preprocess.train_offsets": [1, 3], "synth.simcol.test_frames": 6},
     ["synth.simcol.test_frames", "train_offsets = 6"]),
    ({"ray.num_workers": 3, "ray.cpus_per_worker": 1.0, "ray.num_cpus": 2},
     ["ray.num_workers x ray.cpus_per_worker = 3 x 1 = 3 CPUs", "ray.num_cpus = 2"]),
    ({"ray.num_workers": 64}, ["ray.num_workers (64)", "preprocess.shard_multiple (4)"]),
    ({"eval.test_sets": {"kitti_test": {"dataset": "kitti"}}}, ["eval.test_sets.kitti_test.dataset", "'kitti'"]),
    ({"eval.test_sets": {"simcol.test": {"dataset": "simcol"}}}, ["eval.test_sets", "'simcol.test'"]),
    ({"eval.test_sets": {"simcol": {"dataset": "simcol", "split": "testing"}}}, ["eval.test_sets.simcol.split"]),
]


@pytest.mark.parametrize(("settings", "named"), CONTRADICTIONS, ids=lambda x: str(x))
def test_contradicting_settings_name_every_key(settings, named):
    with pytest.raises(ConfigError) as caught:
        params_from_dict(defaults_with(settings))
    for text in named:
        assert text in str(caught.value)


def test_local_cpu_budget_applies_only_to_a_local_ray():
    # On a cluster (ray.address set) ray.num_cpus is unused; the cluster's size is checked once connected.
    cluster = {"ray.address": "auto", "ray.num_workers": 4, "ray.cpus_per_worker": 8.0, "ray.num_cpus": 2}
    assert params_from_dict(defaults_with(cluster)).ray.num_workers == 4
    fits = {"ray.num_workers": 2, "ray.cpus_per_worker": 1.5, "ray.num_cpus": 3}
    assert params_from_dict(defaults_with(fits)).ray.num_workers == 2


@pytest.mark.parametrize("key", ["train.lr", "model.max_depth", "ray.cpus_per_worker", "train.grad_clip",
                                 "loss.kl_weight"])
@pytest.mark.parametrize("value", [".inf", ".nan", "-.inf"])
def test_non_finite_numbers_are_refused_naming_the_key(tmp_path, key: str, value: str) -> None:
    path = tmp_path / "params.yaml"
    path.write_text("seed: 0\n")
    with pytest.raises(ConfigError, match=f"{key} must be a finite number"):
        load_params(path, [f"{key}={value}"])


def test_a_sections_copy_names_the_dotted_key_it_refuses():
    params = Params()
    with pytest.raises(ConfigError, match=r"^train\.lr must be > 0, got -2$"):
        params.train.replace(lr=-2)
    with pytest.raises(ConfigError, match=r"^data\.simcol\.intrinsics must be a 3x3 matrix"):
        params.data.simcol.replace(intrinsics=[[1, 2], [3]])
    with pytest.raises(ConfigError, match=r"^eval\.test_sets\.\*\.split must be one of"):
        params.eval.test_sets["simcol_12"].replace(split="tests")
