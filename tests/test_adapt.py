"""``endoflow adapt``: a model fitted to one clip explains its held-out frames better, names its parent, and runs
from the command line as ``reconstruct --adapt`` does; bad input says what to give."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from endoflow.cli import main as cli
from endoflow.config import DATASETS
from endoflow.io import file_sha256
from endoflow.models.endoflow_model import build_model, load_trained_model
from endoflow.models.model_file import ModelRecord, load_model_file, save_model_file
from endoflow.io import OutputFolderError
from endoflow.reconstruction.frames import FrameRange, open_frames
from endoflow.reconstruction.reconstruct import Adaptation, ReconstructOptions, reconstruct
from endoflow.synth.writers import synthesize_layout
from endoflow.training.adapt import AdaptOptions, adapt, fits_better, input_sequence
from tests.module_temp import ModuleTemp
from tests.small_model import small_model_params
from tests.test_reconstruct import default_baselines

SIZE = 64


@pytest.fixture(scope="module")
def clips(module_tmp: ModuleTemp) -> Path:
    """The built-in video, 40 frames a clip: the colon seen through an endoscope's circle, as ``clip_000.mp4``
    (intrinsics unknown) and as the frames of ``clip_001/`` (with its intrinsics beside it)."""
    root = module_tmp("clips")
    synthesize_layout("video", root, sequences=2, frames=40, size=SIZE, seed=0, params=small_model_params(SIZE),
                      workers=1, device="cpu")
    return root


@pytest.fixture(scope="module")
def clip(clips: Path) -> Path:
    return clips / "clip_000.mp4"


@pytest.fixture(scope="module")
def model_file(module_tmp: ModuleTemp) -> Path:
    params = small_model_params(SIZE)
    params.train = params.train.replace(batch_size=4, lr=3e-3)  # adapted at a tenth of it
    torch.manual_seed(0)
    path = module_tmp("model") / "endoflow.pt"
    save_model_file(path, ModelRecord(params, build_model(params, None).state_dict(), 3, {}, "0" * 32,
                                      default_baselines()))
    return path


def test_adapting_lowers_the_held_out_photometric_error_and_names_the_parent(clips: Path, model_file: Path,
                                                                               tmp_path: Path):
    params = load_model_file(model_file).params
    sequence = input_sequence(clips / "clip_001", None, params)
    assert sequence.intrinsics_known and sequence.dataset == "video"  # its intrinsics file beside it
    out = tmp_path / "adapted.pt"
    summary = adapt(sequence, model_file, out, AdaptOptions(steps=25, device="cpu"))
    assert summary["held_out_photometric_after"] < 0.8 * summary["held_out_photometric_before"]
    assert (summary["frames"], summary["held_out_frames"]) == (40, 8) and summary["lr"] == pytest.approx(3e-4)
    record = load_model_file(out)
    assert record.adapted_from["parent"] == {"model": str(model_file), "sha256": file_sha256(model_file),
                                             "mlflow_run_id": "0" * 32}
    assert record.val == {"val_photometric": summary["held_out_photometric_after"]}
    # the same input, options and seed: the same model, to the bit (a few steps take every random draw there is)
    for name in ("first.pt", "second.pt"):
        adapt(sequence, model_file, tmp_path / name, AdaptOptions(steps=3, device="cpu"))
    first, second = load_model_file(tmp_path / "first.pt").state, load_model_file(tmp_path / "second.pt").state
    assert all(torch.equal(first[key], second[key]) for key in first)
    assert not all(torch.equal(first[key], record.state[key]) for key in first)  # 3 steps are not 25


def test_a_video_of_unknown_intrinsics_learns_its_cameras(clip: Path, model_file: Path, tmp_path: Path):
    params = load_model_file(model_file).params
    sequence = input_sequence(clip, None, params)
    assert not sequence.intrinsics_known
    summary = adapt(sequence, model_file, tmp_path / "adapted.pt", AdaptOptions(steps=3, device="cpu"))
    model, _ = load_trained_model(tmp_path / "adapted.pt", torch.device("cpu"))
    # the video camera's intrinsics were learned on the video, the others left as they were
    assert model.intrinsics.learned(DATASETS.index("video")) and not model.intrinsics.learned(DATASETS.index("simcol"))
    assert summary["intrinsics"] != sequence.K.tolist()


def test_adapt_runs_from_the_command_line_and_reconstruct_adapts_first(clip: Path, model_file: Path,
                                                                       tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli(["adapt", str(clip), "--model", str(model_file), "--out", "adapted.pt", "--steps", "2",
                "--no-mlflow"]) == 0
    assert load_model_file(tmp_path / "adapted.pt").adapted_from["steps"] == 2
    assert cli(["reconstruct", str(clip), "--model", str(model_file), "--out", "recon", "--adapt", "2",
                "--no-fusion", "--stop", "12"]) == 0
    adapted = load_model_file(tmp_path / "recon" / "model_adapted.pt")
    assert adapted.adapted_from["steps"] == 2
    summary = json.loads((tmp_path / "recon" / "reconstruction.json").read_text())
    assert summary["frames"] == 12 and summary["intrinsics"].startswith("learned by the model for its 'video'")
    # the summary names the kept model, not the scratch file it was adapted into, and what it was adapted from
    assert summary["model"] == "model_adapted.pt" and summary["adapted_from"] == adapted.adapted_from
    assert summary["adaptation"]["kept"] and summary["adaptation"]["steps"] == 2


def test_reconstruct_keeps_the_model_as_trained_where_the_fit_explains_the_held_out_frames_worse(
        clip: Path, model_file: Path, tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    worse = {"held_out_photometric_before": 0.05, "held_out_photometric_after": 0.06}
    monkeypatch.setattr("endoflow.cli._run_adaptation", lambda *args: {"steps": 2, **worse})
    assert cli(["reconstruct", str(clip), "--model", str(model_file), "--out", "recon", "--adapt", "2",
                "--no-fusion", "--stop", "12"]) == 0
    assert ("does not explain the held-out frames better than the model as trained (photometric error 0.0500 -> "
            "0.0600)") in capsys.readouterr().err
    summary = json.loads((tmp_path / "recon" / "reconstruction.json").read_text())
    assert summary["model"] == str(model_file) and "adapted_from" not in summary
    assert summary["adaptation"] == {"steps": 2, **worse, "kept": False}
    assert not (tmp_path / "recon" / "model_adapted.pt").exists()


def test_a_kept_fit_never_replaces_the_folder_that_holds_the_model_it_started_from(
        clip: Path, model_file: Path, tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli(["reconstruct", str(clip), "--model", str(model_file), "--out", "recon", "--no-fusion",
                "--stop", "8"]) == 0
    mine = tmp_path / "recon" / "mine.pt"  # a model kept in an earlier reconstruction's folder
    mine.write_bytes(model_file.read_bytes())

    fits: list[Path] = []

    def kept_fit(args, model_path: Path, out: Path, options) -> dict:
        fits.append(out)
        out.write_bytes(Path(model_path).read_bytes())
        return {"steps": 2, "held_out_photometric_before": 0.06, "held_out_photometric_after": 0.05}

    monkeypatch.setattr("endoflow.cli._run_adaptation", kept_fit)
    assert cli(["reconstruct", str(clip), "--model", str(mine), "--out", "recon", "--adapt", "2", "--force",
                "--no-fusion", "--stop", "8"]) != 0
    assert "which this run reads" in capsys.readouterr().err
    assert mine.read_bytes() == model_file.read_bytes()
    assert not fits  # refused before the fit, which takes minutes

    # and were the folder checked only before the fit, reconstruct's own check still refuses it
    fitted = tmp_path / "fit.pt"
    fit = kept_fit(None, mine, fitted, None)
    with pytest.raises(OutputFolderError, match="which this run reads"):
        reconstruct(open_frames(clip, None, load_model_file(mine).params), None, mine, tmp_path / "recon",
                    ReconstructOptions(fuse=False, force=True, frames=FrameRange(stop=8)),
                    adaptation=Adaptation.of(fitted, fit, kept=True))
    assert mine.read_bytes() == model_file.read_bytes()


@pytest.mark.parametrize("before, after, better", [(0.06, 0.05, True), (0.05, 0.05, False), (0.05, float("nan"), False),
                                                   (float("nan"), 0.05, False)])
def test_a_fit_is_better_only_where_its_held_out_error_is_lower(before: float, after: float, better: bool):
    fit = {"steps": 2, "held_out_photometric_before": before, "held_out_photometric_after": after}
    assert fits_better(fit) is better
    # what reconstruction.json records: JSON has no NaN, so an error that is not a number is null
    record = Adaptation.of(Path("fit.pt"), fit, better).record()
    assert json.loads(json.dumps(record, allow_nan=False))["kept"] is better
    assert record["held_out_photometric_after"] == (None if np.isnan(after) else after)


def test_too_few_frames_or_the_model_itself_as_output_are_refused(clip: Path, model_file: Path, tmp_path: Path):
    params = load_model_file(model_file).params
    sequence = input_sequence(clip, None, params)
    with pytest.raises(Exception, match="5 frames selected: adapting needs at least 6"):
        adapt(sequence, model_file, tmp_path / "a.pt", AdaptOptions(steps=1, stop=5, device="cpu"))
    with pytest.raises(ValueError, match="is the model adapted"):
        adapt(sequence, model_file, model_file, AdaptOptions(steps=1, device="cpu"))
    with pytest.raises(ValueError, match="0 < held_out < 1"):
        AdaptOptions(held_out=1.0)
    assert cli(["adapt", str(tmp_path / "missing.mp4"), "--model", str(model_file), "--out", "x.pt"]) == 2


def test_given_intrinsics_are_used_as_given(clip: Path, model_file: Path, tmp_path: Path):
    params = load_model_file(model_file).params
    sequence = input_sequence(clip, None, params, intrinsics="30,30,31.5,31.5")
    assert sequence.intrinsics_known
    np.testing.assert_allclose(sequence.K, [[30, 0, 31.5], [0, 30, 31.5], [0, 0, 1]])
    summary = adapt(sequence, model_file, tmp_path / "a.pt", AdaptOptions(steps=1, device="cpu"))
    np.testing.assert_allclose(summary["intrinsics"], [[30, 0, 31.5], [0, 30, 31.5], [0, 0, 1]])
