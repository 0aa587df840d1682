"""`endoflow reconstruct --out`: a new, empty or earlier reconstruction folder is replaced; a folder of the user's
is left untouched unless `--force` says otherwise, and the input or a folder holding it never is."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from endoflow.cli import INTERRUPTED
from endoflow.cli import main as cli
from endoflow.reconstruction import reconstruct as reconstruct_module
from endoflow.reconstruction.reconstruct import RECONSTRUCTION_FORMAT, write_frame_outputs
from tests.test_reconstruct import image_folder, k_numbers, model_file, params, scene  # noqa: F401 (fixtures)

QUICK = ["--stop", "2", "--no-fusion"]


def reconstruct(input_path: Path, model: Path, out: Path, *extra: str) -> int:
    return cli(["reconstruct", str(input_path), "--model", str(model), "--out", str(out), *QUICK, *extra])


def user_folder(path: Path) -> Path:
    (path / "sub").mkdir(parents=True)
    (path / "thesis.txt").write_text("four years of work")
    (path / "sub" / "notes.md").write_text("more")
    return path


def contents(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_folder_of_the_users_is_left_untouched_and_the_error_says_what_it_holds_and_how_to_proceed(
        scene: Path, model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = user_folder(tmp_path / "mine")
    before = contents(out)
    assert reconstruct(scene, model_file, out, "--sequence", "S1") == 2
    error = capsys.readouterr().err
    assert f"{out}: will not replace a folder that is not an earlier endoflow reconstruction" in error
    assert "it holds sub/, thesis.txt" in error and "or pass --force to replace it" in error
    assert contents(out) == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no staging left behind


@pytest.mark.parametrize("where", ["the input", "a folder holding the input"])
def test_the_input_folder_is_never_replaced_even_with_force(scene: Path, params, model_file: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture, where: str) -> None:
    frames = image_folder(scene, params, tmp_path / "frames")
    before = contents(frames)
    out = frames if where == "the input" else tmp_path
    code = reconstruct(frames, model_file, out, "--intrinsics", k_numbers(scene, params), "--force")
    assert code == 2
    relation = "is" if where == "the input" else "holds"
    assert f"{out}: will not replace this folder: it {relation} {frames}, which this run reads" in \
        capsys.readouterr().err
    assert contents(frames) == before


def test_a_folder_holding_the_model_is_never_replaced(scene: Path, model_file: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    assert reconstruct(scene, model_file, model_file.parent, "--sequence", "S1", "--force") == 2
    assert f"it holds {model_file}, which this run reads" in capsys.readouterr().err
    assert model_file.is_file()


def test_force_replaces_a_folder_of_other_files_and_the_next_run_replaces_that_earlier_reconstruction(
        scene: Path, model_file: Path, tmp_path: Path) -> None:
    out = user_folder(tmp_path / "scratch")
    assert reconstruct(scene, model_file, out, "--sequence", "S1", "--force") == 0
    assert not (out / "thesis.txt").exists()
    assert json.loads((out / "reconstruction.json").read_text())["format"] == RECONSTRUCTION_FORMAT
    (out / "depth" / "000009.png").write_bytes(b"from a longer earlier run")
    assert reconstruct(scene, model_file, out, "--sequence", "S1", "--start", "1", "--stop", "3") == 0
    assert sorted(p.name for p in (out / "depth").glob("*.png")) == ["000001.png", "000002.png"]


def test_a_reconstruction_json_without_endoflows_format_marker_is_not_taken_for_one(
        scene: Path, model_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "look-alike"
    out.mkdir()
    (out / "reconstruction.json").write_text(json.dumps({"frames": 3, "format": "someone else's"}))
    assert reconstruct(scene, model_file, out, "--sequence", "S1") == 2
    assert [p.name for p in out.iterdir()] == ["reconstruction.json"]


def test_ctrl_c_ends_with_one_line_and_leaves_the_earlier_reconstruction_as_it_was(
        scene: Path, model_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "earlier"
    assert reconstruct(scene, model_file, out, "--sequence", "S1") == 0
    before = contents(out)
    capsys.readouterr()
    written = []

    def write_then_interrupt(*args, **kwargs) -> None:
        if written:
            raise KeyboardInterrupt  # as Ctrl-C raises it, between the second frame's outputs and the third's
        written.append(write_frame_outputs(*args, **kwargs))

    monkeypatch.setattr(reconstruct_module, "write_frame_outputs", write_then_interrupt)
    assert reconstruct(scene, model_file, out, "--sequence", "S1", "--stop", "3") == INTERRUPTED == 130
    assert capsys.readouterr().err.splitlines()[-1] == "endoflow: interrupted"
    assert written and contents(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["earlier"]  # no staging left behind
