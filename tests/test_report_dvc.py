"""`endoflow report` against a real DVC project: it lists the experiments through DVC's Python API, reads each
one's full evaluation from DVC's cache at its revision, works without `dvc` on PATH, and says why when it cannot
list experiments."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.module_temp import ModuleTemp
from tests.project_clone import VENV_BIN, pipeline_env, run

# A stand-in for the evaluate stage: the Abs Rel it writes depends on the ablation switch, like a real model's.
EVALUATE = """
import json, pathlib, yaml
params = yaml.safe_load(open("params.yaml"))
folder = pathlib.Path("predictions/simcol_12")
folder.mkdir(parents=True, exist_ok=True)
abs_rel = 0.1 if params["model"]["latent_bank"] else 0.2
(folder / "evaluation.json").write_text(json.dumps({
    "test_set": "simcol_12",
    "depth_paper": {"model": {"abs_rel": abs_rel}},
    "pose_simcol": {"model": {"rte": 0.03, "rot": 1.0}}}))
"""
DVC_YAML = """stages:
  evaluate:
    cmd: python evaluate.py
    deps: [evaluate.py]
    params: [model.latent_bank]
    outs: [predictions/simcol_12]
"""
PARAMS = """model:
  latent_bank: true
  pose_vae: true
eval:
  test_sets:
    simcol_12:
      dataset: simcol
      groups: [SyntheticColon_I]
"""


def without_venv_on_path(env: dict[str, str]) -> dict[str, str]:
    """The environment of a user who calls `.venv/bin/endoflow` without activating the venv."""
    path = [entry for entry in env["PATH"].split(os.pathsep) if Path(entry) != VENV_BIN]
    return {**env, "PATH": os.pathsep.join(path)}


@pytest.fixture(scope="module")
def project(module_tmp: ModuleTemp) -> Path:
    root = module_tmp("report_project")
    env = pipeline_env("report")
    (root / "evaluate.py").write_text(EVALUATE)
    (root / "dvc.yaml").write_text(DVC_YAML)
    (root / "params.yaml").write_text(PARAMS)
    run(["git", "init", "-q"], root, env)
    run(["dvc", "init", "-q"], root, env)
    run(["dvc", "repro", "-q"], root, env)
    run(["git", "add", "-A"], root, env)
    run(["git", "commit", "-qm", "baseline"], root, env)
    run(["dvc", "exp", "run", "-q", "-n", "no-bank", "-S", "model.latent_bank=false"], root, env)
    return root


def test_report_lists_experiments_without_dvc_on_path(project: Path):
    env = without_venv_on_path(pipeline_env("report"))
    assert subprocess.run(["which", "dvc"], env=env, capture_output=True).returncode != 0
    report = run([str(VENV_BIN / "endoflow"), "report"], project, env).stdout
    ablation = report.split("## Ablation summary")[1]
    # the workspace holds the last experiment's outputs; the baseline commit and the experiment are read at
    # their revisions from DVC's cache
    assert "| no-bank (bank off, VAE on)" in ablation and "0.2000" in ablation
    baseline = [line for line in ablation.splitlines() if "(bank on, VAE on)" in line and "workspace" not in line]
    assert baseline and "0.1000" in baseline[0], ablation


def test_report_outside_a_dvc_project_says_why_it_shows_the_workspace_only(tmp_path: Path):
    folder = tmp_path / "predictions" / "simcol_12"
    folder.mkdir(parents=True)
    (folder / "evaluation.json").write_text(json.dumps({"depth_paper": {"model": {"abs_rel": 0.3}}}))
    result = run([str(VENV_BIN / "endoflow"), "report"], tmp_path, pipeline_env("report"))
    assert "workspace only" in result.stderr and "is not a DVC project" in result.stderr
    assert "| workspace" in result.stdout


def test_experiments_of_an_earlier_commit_are_reported_with_all_commits(project: Path, tmp_path: Path):
    """A sweep queued before a commit hangs its experiments on the earlier commit: HEAD's list misses them."""
    env = pipeline_env("report")
    copy = tmp_path / "project"
    shutil.copytree(project, copy, symlinks=True)
    run(["git", "commit", "-q", "--allow-empty", "-m", "a later commit"], copy, env)
    endoflow = str(VENV_BIN / "endoflow")
    assert "no-bank (bank off" not in run([endoflow, "report"], copy, env).stdout
    assert "| no-bank (bank off, VAE on)" in run([endoflow, "report", "--all-commits"], copy, env).stdout
