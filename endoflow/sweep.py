"""Studies as DVC experiments, each configuration with each seed, queued in DVC's experiment queue and run one
after another by ``dvc queue start``: the paper's Table 3 (``ablation``: :data:`ABLATIONS`), the VAE study
(``vae``: :data:`VAE_STUDY`), the motion study (``motion``: :data:`MOTION_STUDY`) and the mask study (``mask``:
:data:`MASK_STUDY`).

Each experiment reproduces the pipeline up to the ``evaluate`` stages (:data:`SWEEP_TARGET`), Table 3's
metrics; reconstruction is left out (``dvc exp apply`` then ``dvc repro`` makes it for a chosen run).

Each experiment is named ``<configuration>-seed<k>`` and sets every switch it relies on, the two ablation
switches and every setting a study varies (:data:`~endoflow.report.STUDY_SETTINGS`; ``-S`` edits the queued
copy's ``params.yaml`` only), so that no experiment inherits a setting from the workspace. DVC runs queued
experiments in temporary copies of the project; the MLflow store and Ray's checkpoints stay in the project
(:func:`endoflow.locations.home_project`). One worker at a time (``-j 1``): the embedded MLflow store is one
SQLite file, and one training already uses every core. When the queue is done, ``endoflow report`` aggregates
the runs by configuration over seeds.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterable

from endoflow.config import ConfigError, load_params
from endoflow.report import ABLATIONS, DEFAULT_KL_WEIGHT, STUDY_SETTINGS

SWEEP_TARGET = "evaluate"
# The VAE study (docs/method.md): the full model with the warp's sampling or the KL taken away, and beta over
# decades. Beside the ablation sweep's full and no-vae runs of the same seeds it tells what the VAE contributes.
VAE_STUDY = (("vae-mean-warp", {"model.pose_sample": False}), ("vae-beta0", {"loss.kl_weight": 0.0}),
             ("vae-beta1e-4", {"loss.kl_weight": 1e-4}), ("vae-beta1e-3", {"loss.kl_weight": 1e-3}))
# The motion study (docs/results.md): the full model as it is, trained on a mixture of frame offsets, with the
# depth consistency between neighbouring frames (SC-SfMLearner's weight), with both, and with a quarter of the
# triplets played backwards (half of them left the pose network, which starts blind to the direction, with no
# net signal: it learned no motion at all, seed 0).
MIXED_OFFSETS = {"preprocess.train_offsets": [1, 2, 3]}
CONSISTENCY = {"loss.geometry_weight": 0.5}
REVERSAL = {"train.time_reversal": 0.25}
MOTION_STUDY = (("motion-base", {}), ("motion-offsets", MIXED_OFFSETS), ("motion-geometry", CONSISTENCY),
                ("motion-both", {**MIXED_OFFSETS, **CONSISTENCY}), ("motion-reversal25", REVERSAL))
# The mask study (docs/results.md): auto-masking drops the far lumen from the depth's loss; the full model as it is,
# without the mask, and with the mask kept for the pose alone.
MASK_STUDY = (("mask-base", {}), ("mask-off", {"loss.automask": False}),
              ("mask-pose-only", {"loss.automask_depth": False}))
STUDIES = ("ablation", "vae", "motion", "mask")
STUDY_CHANGES = {"vae": VAE_STUDY, "motion": MOTION_STUDY, "mask": MASK_STUDY}


class SweepError(RuntimeError):
    """The sweep's params do not validate (nothing is queued then), or a ``dvc`` command of the sweep failed (DVC
    has printed why)."""


def sweep_commands(seeds: Iterable[int], study: str = "ablation") -> list[list[str]]:
    """The ``dvc`` arguments that queue every configuration of ``study`` (:data:`STUDIES`) with every seed,
    seed by seed."""
    return [["exp", "run", "--queue", "-n", f"{name}-seed{seed}",
             *(word for key, value in settings.items() for word in ("-S", f"{key}={_value(value)}")),
             "-S", f"seed={seed}", SWEEP_TARGET]
            for seed in seeds for name, settings in study_configurations(study)]


def study_configurations(study: str) -> list[tuple[str, dict[str, Any]]]:
    """``study``'s configurations as (name, {dotted params key: value}): the two ablation switches and every study
    setting, at its default unless the configuration changes it."""
    if study not in STUDIES:
        raise ValueError(f"study: expected one of {', '.join(STUDIES)}, got {study!r}")
    defaults = {setting.key: setting.default for setting in STUDY_SETTINGS}
    if study == "ablation":
        return [(name, {"model.latent_bank": bank, "model.pose_vae": vae, **defaults}) for name, bank, vae in ABLATIONS]
    return [(name, {"model.latent_bank": True, "model.pose_vae": True, **defaults, **changed})
            for name, changed in STUDY_CHANGES[study]]


def _value(value: Any) -> str:
    """A value as ``-S`` takes it (YAML: ``true``, ``1e-05``, ``[1,2,3]``, ``null``)."""
    return repr(value) if isinstance(value, float) else json.dumps(value, separators=(",", ":"))


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
