"""dvc.yaml's plots: every chart names its x and its y columns, the model beside its baselines, for every test set
and reconstructed sequence of the params and none other (DVC cannot loop over them in its top-level plots:
`make dvc-plots` writes them from params.yaml, for the default params and for every preset alike); stage plots are
pictures only, so that `dvc plots show` never charts a default column; the HTML page DVC writes says why charts
are missing offline and shows the training's figures first, then the evaluation's, then the reconstruction's."""

from __future__ import annotations

import difflib
import json
import re
from pathlib import Path

import pytest
import yaml

from endoflow.config import load_params, params_to_dict
from endoflow.evaluation.evaluate import DEPTH_METHODS, POSE_METHODS
from endoflow.reconstruction.measure import PATH_ROWS
from tests.project_clone import PROJECT
from tools.dvc_plots import COMMAND, rewrite_plots

PARAMS_FILES = [PROJECT / "params.yaml", *sorted((PROJECT / "presets").glob("*.yaml"))]


def top_level_plots(params_file: Path = PROJECT / "params.yaml") -> dict[str, dict]:
    """dvc.yaml's charts as `make dvc-plots` writes them for ``params_file``."""
    dvc = yaml.safe_load(rewrite_plots((PROJECT / "dvc.yaml").read_text(), load_params(params_file)))
    return {name: props for entry in dvc["plots"] for name, props in entry.items()}


def resolved(text: str, params_file: Path) -> str:
    """``text`` with the ``${section.key}`` references of the charts resolved as DVC does."""
    params = params_to_dict(load_params(params_file))
    for section in ("train", "eval", "reconstruct"):
        for key, value in params[section].items():
            if isinstance(value, str):
                text = text.replace(f"${{{section}.{key}}}", value)
    return text


def charted_columns(params_file: Path) -> dict[str, set[str]]:
    """``{file: columns}`` over every top-level chart, paths resolved with ``params_file``."""
    columns: dict[str, set[str]] = {}
    for props in top_level_plots(params_file).values():
        assert set(props) >= {"x", "y"}, props
        for path, names in props["y"].items():
            columns.setdefault(resolved(path, params_file), set()).update(names)
    return columns


@pytest.mark.parametrize("params_file", PARAMS_FILES, ids=lambda path: path.name)
def test_every_test_set_is_charted_with_the_model_beside_its_baselines(params_file: Path):
    params = load_params(params_file)
    columns = charted_columns(params_file)
    for test_set in params.eval.test_sets:
        charted = columns.get(f"{params.eval.predictions}/{test_set}/per_frame.csv", set())
        assert {f"abs_rel_{m}" for m in DEPTH_METHODS} | {f"rte_{m}" for m in POSE_METHODS} <= charted, test_set


@pytest.mark.parametrize("params_file", PARAMS_FILES, ids=lambda path: path.name)
def test_every_reconstructed_sequence_is_charted_beside_constant_velocity(params_file: Path):
    params = load_params(params_file)
    columns = charted_columns(params_file)
    for name in params.reconstruct.sequences:
        assert columns.get(f"{params.reconstruct.out}/{name}/path_errors.csv") == set(PATH_ROWS), name


def test_the_committed_charts_are_those_of_the_committed_params():
    text = (PROJECT / "dvc.yaml").read_text()
    written = rewrite_plots(text, load_params(PROJECT / "params.yaml"))
    change = list(difflib.unified_diff(text.splitlines(), written.splitlines(), "dvc.yaml", "params", lineterm=""))
    assert written == text, (f"dvc.yaml's charts are not params.yaml's test sets and sequences: run `{COMMAND}` "
                             f"(python -m tools.dvc_plots)\n" + "\n".join(change[:40]))


def test_a_test_set_or_sequence_left_out_of_the_params_has_no_chart():
    """A chart of a file the pipeline no longer writes is an error in `dvc plots show`."""
    params = load_params(PROJECT / "params.yaml")
    params.eval.test_sets = {"simcol_3": params.eval.test_sets["simcol_3"]}
    params.reconstruct.sequences = {"simcol_O1": params.reconstruct.sequences["simcol_O1"]}
    charted = yaml.safe_load(rewrite_plots((PROJECT / "dvc.yaml").read_text(), params))["plots"]
    tables = {path for entry in charted for props in entry.values() for path in props["y"]}
    assert tables == {"${train.plots}/history.csv", "${eval.predictions}/simcol_3/per_frame.csv",
                      "${reconstruct.out}/simcol_O1/path_errors.csv"}


def test_rewriting_keeps_everything_above_the_charts_and_refuses_what_it_would_lose():
    text = (PROJECT / "dvc.yaml").read_text()
    above = text[:text.index("\nplots:\n") + 1]
    assert rewrite_plots(text, load_params(PROJECT / "params.yaml")).startswith(above)
    with pytest.raises(ValueError, match="no top-level block starting with 'plots:'"):
        rewrite_plots(above, load_params(PROJECT / "params.yaml"))
    with pytest.raises(ValueError, match="must be the file's last; 'artifacts:' follows it"):
        rewrite_plots(text + "# the model\nartifacts:\n  endoflow:\n    path: models/endoflow.pt\n",
                      load_params(PROJECT / "params.yaml"))


def test_training_curves_chart_loss_and_validation_error_per_epoch():
    chart = top_level_plots()["training curves"]
    assert chart["x"] == "epoch"
    assert chart["y"] == {"${train.plots}/history.csv": ["train_loss", "val_abs_rel", "val_rmse", "val_photometric"]}


def test_stage_plots_are_pictures_only():
    """A CSV or JSON among a stage's plots would get DVC's default chart (its last column)."""
    stages = yaml.safe_load((PROJECT / "dvc.yaml").read_text())["stages"]
    for name, stage in stages.items():
        for entry in (stage.get("do") or stage).get("plots", []):
            path = entry if isinstance(entry, str) else next(iter(entry))
            assert not path.endswith((".csv", ".json", ".tsv", ".yaml")), (name, path)


def test_the_training_curves_come_first_then_evaluation_then_reconstruction():
    """The charts in dvc.yaml's order; the page's figures (PNG) by its FIGURE_FOLDERS, which dvc-render would list
    by path (the evaluation's before the training's)."""
    names = list(top_level_plots())
    stage_of = ["training" if name == "training curves" else "reconstruction" if "camera path" in name
                else "evaluation" for name in names]
    assert stage_of == sorted(stage_of, key=["training", "evaluation", "reconstruction"].index), names
    page = (PROJECT / ".dvc" / "plots_page.html").read_text()
    folders = json.loads(re.search(r"FIGURE_FOLDERS = (\[.*?\]);", page).group(1))
    for params_file in PARAMS_FILES:
        params = load_params(params_file)
        pipeline = [params.train.plots, params.latent_bank.plots, params.eval.plots, params.reconstruct.plots]
        assert folders == [f"{folder}/" for folder in pipeline], params_file.name


def test_the_plots_page_says_why_charts_are_missing_offline():
    config = (PROJECT / ".dvc" / "config").read_text()
    assert "html_template = plots_page.html" in config
    page = (PROJECT / ".dvc" / "plots_page.html").read_text()
    assert "{plot_divs}" in page and "{scripts}" in page
    assert "cannot be drawn" in page and 'typeof vegaEmbed === "undefined"' in page
