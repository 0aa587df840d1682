"""A fresh copy of the project as a git repository, for the tests that run `dvc repro` as a user does."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent


def project_files() -> list[str]:
    """What a clean clone holds: tracked files plus untracked ones git does not ignore."""
    listing = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=PROJECT, capture_output=True, text=True, check=True,
    ).stdout
    return [name for name in listing.split("\0") if name and (PROJECT / name).is_file()]


def pipeline_env(author: str) -> dict[str, str]:
    """The environment stage commands need: the venv's `python` first on PATH, no telemetry, a git identity."""
    return {
        **os.environ,
        "PATH": f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}",
        "DVC_NO_ANALYTICS": "1",
        "RAY_USAGE_STATS_ENABLED": "0",
        "GIT_AUTHOR_NAME": author, "GIT_AUTHOR_EMAIL": f"{author}@example.invalid",
        "GIT_COMMITTER_NAME": author, "GIT_COMMITTER_EMAIL": f"{author}@example.invalid",
    }


def run(args: list[str], cwd: Path, env: dict[str, str], timeout: int = 900) -> subprocess.CompletedProcess:
    result = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{' '.join(args)} failed:\n{result.stdout[-6000:]}\n{result.stderr[-6000:]}"
    return result


def clone_project(clone: Path, params_text: str, env: dict[str, str]) -> None:
    """Copy the project to ``clone`` with ``params_text`` as its params.yaml and dvc.yaml's charts written for it (as
    `make repro` writes them), committed in a new git repository."""
    # imported here: the modules that want only PROJECT (the docs' link check) need not load torch through them
    from endoflow.config import load_params
    from tools.dvc_plots import rewrite_plots

    for name in project_files():
        (clone / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(PROJECT / name, clone / name)
    (clone / "params.yaml").write_text(params_text)
    dvc_yaml = clone / "dvc.yaml"
    dvc_yaml.write_text(rewrite_plots(dvc_yaml.read_text(), load_params(clone / "params.yaml")))
    run(["git", "init", "-q"], clone, env)
    run(["git", "add", "-A"], clone, env)
    run(["git", "commit", "-q", "-m", "params"], clone, env)
