"""Studies as DVC experiments, each configuration with each seed, queued in DVC's experiment queue and run one
after another by ``dvc queue start``: the paper's Table 3 (``ablation``: :data:`ABLATIONS`) and the VAE study
(``vae``: :data:`VAE_STUDY`).

Each experiment reproduces the pipeline up to the ``evaluate`` stages (:data:`SWEEP_TARGET`), Table 3's
metrics; reconstruction is left out (``dvc exp apply`` then ``dvc repro`` makes it for a chosen run).

Each experiment is named ``<configuration>-seed<k>`` and sets every switch it relies on, the two ablation
switches and the VAE study's two settings (``-S`` edits the queued copy's ``params.yaml`` only). DVC runs queued
experiments in temporary copies of the project; the MLflow store and Ray's checkpoints stay in the project
(:func:`endoflow.locations.home_project`). One worker at a time (``-j 1``): the embedded MLflow store is one
SQLite file, and one training already uses every core. When the queue is done, ``endoflow report`` aggregates
the runs by configuration over seeds.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Iterable

from endoflow.config import ConfigError, load_params
from endoflow.report import ABLATIONS, DEFAULT_KL_WEIGHT, DEFAULT_POSE_SAMPLE

SWEEP_TARGET = "evaluate"
# The VAE study (docs/method.md): the full model with the warp's sampling or the KL taken away, and beta over
# decades: (name, model.pose_sample, loss.kl_weight). Beside the ablation sweep's full and no-vae runs of the same
# seeds it tells what the VAE contributes.
VAE_STUDY = (("vae-mean-warp", False, DEFAULT_KL_WEIGHT), ("vae-beta0", True, 0.0), ("vae-beta1e-4", True, 1e-4),
             ("vae-beta1e-3", True, 1e-3))
STUDIES = ("ablation", "vae")


class SweepError(RuntimeError):
    """The sweep's params do not validate (nothing is queued then), or a ``dvc`` command of the sweep failed (DVC
    has printed why)."""


def sweep_commands(seeds: Iterable[int], study: str = "ablation") -> list[list[str]]:
    """The ``dvc`` arguments that queue every configuration of ``study`` (:data:`STUDIES`) with every seed,
    seed by seed."""
    return [["exp", "run", "--queue", "-n", f"{name}-seed{seed}", "-S", f"model.latent_bank={_flag(bank)}",
             "-S", f"model.pose_vae={_flag(vae)}", "-S", f"model.pose_sample={_flag(sample)}",
             "-S", f"loss.kl_weight={beta!r}", "-S", f"seed={seed}", SWEEP_TARGET]
            for seed in seeds for name, bank, vae, sample, beta in study_configurations(study)]


def study_configurations(study: str) -> list[tuple[str, bool, bool, bool, float]]:
    """``study``'s configurations as (name, model.latent_bank, model.pose_vae, model.pose_sample,
    loss.kl_weight); the ablations keep the VAE study's defaults."""
    if study not in STUDIES:
        raise ValueError(f"study: expected one of {', '.join(STUDIES)}, got {study!r}")
    if study == "ablation":
        return [(name, bank, vae, DEFAULT_POSE_SAMPLE, DEFAULT_KL_WEIGHT) for name, bank, vae in ABLATIONS]
    return [(name, True, True, sample, beta) for name, sample, beta in VAE_STUDY]


def _flag(value: bool) -> str:
    return str(value).lower()


def check_sweep_params(project_root: str | Path, commands: list[list[str]]) -> None:
    """Validate the project's ``params.yaml`` with each experiment's ``-S`` changes before anything is queued: a
    typo would otherwise fail every queued experiment, one after another, hours later."""
    path = Path(project_root) / "params.yaml"
    for arguments in commands:
        changes = [value for flag, value in zip(arguments, arguments[1:]) if flag == "-S"]
        try:
            load_params(path, changes)
        except ConfigError as exc:
            name = arguments[arguments.index("-n") + 1]
            raise SweepError(f"{exc} (with experiment {name}'s changes {' '.join(changes)}); nothing was "
                             f"queued") from None


def stage_environment() -> dict[str, str]:
    """The environment of the ``dvc`` commands: stage commands call ``python``, and the queue worker started here
    runs them, so this interpreter's folder comes first on PATH (as in ``make repro``), activated or not."""
    environment = dict(os.environ)
    environment["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), environment.get("PATH", "")])
    return environment


def run_sweep(project_root: str | Path, seeds: Iterable[int], start: bool = True, study: str = "ablation") -> None:
    """Queue ``study``'s sweep in the DVC project at ``project_root`` and, with ``start``, start one queue
    worker."""
    dvc = [sys.executable, "-m", "dvc"]
    check_sweep_params(project_root, sweep_commands(seeds, study))
    commands = sweep_commands(seeds, study) + ([["queue", "start", "-j", "1"]] if start else [])
    for arguments in commands:
        print(f"[sweep] dvc {' '.join(arguments)}", flush=True)
        exit_code = subprocess.run(dvc + arguments, cwd=project_root, env=stage_environment()).returncode
        if exit_code != 0:
            raise SweepError(f"`dvc {' '.join(arguments)}` failed with exit code {exit_code} in "
                             f"{Path(project_root).resolve()} (DVC says why above); run the sweep at the root of a "
                             "DVC project (experiments queued before the failure stay queued: `dvc queue status`)")
    print("[sweep] follow with `dvc queue status` and `dvc queue logs <name>`; when the queue is done, "
          "`endoflow report` gives mean ± sd per configuration", flush=True)
