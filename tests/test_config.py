"""params.yaml is validated once, and every mistake names its key."""

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
)

PROJECT = Path(__file__).resolve().parents[1]


def write_params(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def key_paths(tree: dict, prefix: str = "") -> set[str]:
    paths = set()
    for key, value in tree.items():
        # Test-set entries are user-defined names, not schema keys.
        if isinstance(value, dict) and f"{prefix}{key}" != "eval.test_sets":
            paths |= key_paths(value, f"{prefix}{key}.")
        else:
            paths.add(f"{prefix}{key}")
    return paths


PARAM_FILES = [PROJECT / "params.yaml", *sorted((PROJECT / "presets").glob("*.yaml"))]


@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_parameter_files_are_valid_and_list_every_key(path):
    # DVC tracks params by key, and a user reads the file to learn what can be set: nothing may be implicit.
    load_params(path)
    assert key_paths(yaml.safe_load(path.read_text())) == key_paths(params_to_dict(Params()))


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
