"""The latent bank file: a missing, damaged, unsafe or foreign ``latent_bank.pt`` fails at once, naming the file."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
import torch

from endoflow.errors import DataFormatError
from endoflow.models.latent_bank import (
    GeneratorSpec,
    LatentBankGenerator,
    check_latent_bank_file,
    generator_payload,
    load_generator,
)

SPEC = GeneratorSpec(resolution=8, start_resolution=4, latent_dim=8, style_dim=8, mapping_layers=1,
                     channel_base=32, channel_max=8, conv_init_scale=0.25)


class CreatesAFileWhenUnpickled:
    """A payload that runs code on unpickling: it creates ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').close()",)


@pytest.fixture
def bank(tmp_path: Path) -> Path:
    path = tmp_path / "models" / "latent_bank.pt"
    path.parent.mkdir()
    torch.save(generator_payload(LatentBankGenerator(SPEC)), path)
    return path


def refused(path: Path) -> DataFormatError:
    """The error of both the check and the loader, which must name the file."""
    with pytest.raises(DataFormatError, match=re.escape(str(path))) as error:
        check_latent_bank_file(str(path))
    with pytest.raises(DataFormatError, match=re.escape(str(path))):
        load_generator(str(path))
    return error.value


def test_a_valid_bank_passes_the_check_and_loads(bank: Path):
    check_latent_bank_file(str(bank))
    assert load_generator(bank).spec == SPEC


def test_a_missing_file_is_named(tmp_path: Path):
    path = tmp_path / "models" / "latent_bank.pt"
    with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
        check_latent_bank_file(str(path))


def test_a_truncated_file_is_named(bank: Path):
    bank.write_bytes(bank.read_bytes()[: bank.stat().st_size // 2])
    assert "truncated or corrupt" in str(refused(bank))


@pytest.mark.parametrize("size", [0, 1000])
def test_random_bytes_are_named(bank: Path, size: int):
    bank.write_bytes(os.urandom(size))
    refused(bank)


def test_a_pickled_payload_that_would_run_code_is_refused_without_running_it(bank: Path, tmp_path: Path):
    marker = tmp_path / "created_by_unpickling"
    torch.save({"format": "endoflow.latent_bank/2", "spec": CreatesAFileWhenUnpickled(marker)}, bank)
    torch.load(bank, weights_only=False)  # the payload is live: an unsafe load runs it
    assert marker.exists()
    marker.unlink()

    error = refused(bank)
    assert not marker.exists()
    assert "could run code" in str(error) and "Unsupported global" in str(error)


@pytest.mark.parametrize(
    "payload, problem",
    [
        ({"something": torch.zeros(1)}, "expected a latent bank file of format"),
        ([torch.zeros(3)], "found 'list'"),
        ({"format": "endoflow.latent_bank/1"}, "found 'endoflow.latent_bank/1'"),
        ({"format": "endoflow.latent_bank/2", "spec": {"resolution": 8}}, "'spec' must have the keys"),
    ],
)
def test_a_valid_torch_file_of_another_format_is_named(bank: Path, payload, problem: str):
    torch.save(payload, bank)
    assert problem in str(refused(bank))


def test_weights_that_do_not_fit_the_stored_architecture_are_named(bank: Path):
    payload = torch.load(bank, weights_only=True)
    payload["spec"]["channel_max"] = 4  # the stored weights have 8 channels
    torch.save(payload, bank)
    assert "weights do not fit the stored architecture" in str(refused(bank))
