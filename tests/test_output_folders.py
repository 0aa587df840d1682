"""The one rule for every folder endoflow replaces (`endoflow.io.check_replaceable`): a missing, empty or earlier
output of the same kind is replaced; anything else is refused before any work, unless forced; what the run reads
never is."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from endoflow.io import FIGURE_FOLDER, OutputFolderError, marked_output, staged_directory

EVALUATION = marked_output("the predictions of test set t", "evaluation.json", test_set="t")


def fill(folder: Path) -> None:
    with staged_directory(folder, FIGURE_FOLDER) as staging:
        (staging / "curves.png").write_bytes(b"png")


def test_a_missing_empty_or_earlier_figure_folder_is_replaced(tmp_path: Path) -> None:
    fill(tmp_path / "plots")  # missing
    (tmp_path / "empty").mkdir()
    fill(tmp_path / "empty")
    (tmp_path / "plots" / "old.png").write_bytes(b"an earlier figure")
    fill(tmp_path / "plots")
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == ["curves.png"]


def test_a_folder_with_other_files_is_refused_before_the_block_runs_and_left_as_it_was(tmp_path: Path) -> None:
    plots = tmp_path / "plots"
    (plots / "deep").mkdir(parents=True)
    (plots / "a.png").write_bytes(b"png")
    (plots / "deep" / "thesis.txt").write_text("mine")
    ran = []
    with pytest.raises(OutputFolderError, match=r"plots: will not replace a folder that is not a folder of figures "
                                                r"\(PNG and CSV files only\): it holds a\.png, deep/; choose a new "
                                                r"or empty folder, or move what it holds elsewhere"):
        with staged_directory(plots, FIGURE_FOLDER):
            ran.append(True)
    assert not ran and (plots / "deep" / "thesis.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plots"]


def test_a_folder_filled_by_someone_else_during_the_run_is_refused_at_the_swap(tmp_path: Path) -> None:
    plots = tmp_path / "plots"
    with pytest.raises(OutputFolderError, match="not a folder of figures"):
        with staged_directory(plots, FIGURE_FOLDER) as staging:
            (staging / "curves.png").write_bytes(b"png")
            plots.mkdir()
            (plots / "notes.txt").write_text("written meanwhile")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plots"]


def test_an_output_is_recognised_by_its_marker_file(tmp_path: Path) -> None:
    folder = tmp_path / "t"
    folder.mkdir()
    (folder / "evaluation.json").write_text(json.dumps({"test_set": "other"}))
    with pytest.raises(OutputFolderError, match="not the predictions of test set t"):
        with staged_directory(folder, EVALUATION):
            pass
    (folder / "evaluation.json").write_text(json.dumps({"test_set": "t"}))
    with staged_directory(folder, EVALUATION) as staging:
        (staging / "evaluation.json").write_text("{}")
    assert (folder / "evaluation.json").read_text() == "{}"


def test_force_replaces_anything_but_the_runs_inputs_and_a_file_is_never_taken_for_a_folder(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "thesis.txt").write_text("mine")
    with staged_directory(out, FIGURE_FOLDER, force=True):
        pass
    assert list(out.iterdir()) == []
    (out / "input.png").write_bytes(b"frame")
    with pytest.raises(OutputFolderError, match=r"it holds .*input\.png, which this run reads"):
        with staged_directory(out, FIGURE_FOLDER, force=True, inputs=[out / "input.png"]):
            pass
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputFolderError, match="is a file, not a folder"):
        with staged_directory(tmp_path / "file", FIGURE_FOLDER, force=True):
            pass
