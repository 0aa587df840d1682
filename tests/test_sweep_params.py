"""`endoflow sweep` validates params.yaml with every experiment's changes before it queues anything: a typo
would otherwise fail each queued experiment, one after another, hours later."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from endoflow.cli import main


def test_a_typo_in_params_fails_the_sweep_naming_the_key_and_nothing_is_queued(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text("train:\n  epochz: 3\n")
    commands = []
    monkeypatch.setattr(subprocess, "run", lambda arguments, **_: commands.append(arguments))
    assert main(["sweep", "--seeds", "0", "--no-start"]) == 1
    error = capsys.readouterr().err
    assert "endoflow sweep: error: params.yaml" in error and "train.epochz" in error
    assert "(with experiment full-seed0's changes model.latent_bank=true" in error and "nothing was queued" in error
    assert commands == []
