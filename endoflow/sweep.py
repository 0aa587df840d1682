"""The paper's Table 3 as DVC experiments: each ablation configuration with each seed, queued in DVC's
experiment queue and run one after another by ``dvc queue start``.

Each experiment reproduces the pipeline up to the ``evaluate`` stages (:data:`SWEEP_TARGET`), Table 3's
metrics; reconstruction is left out (``dvc exp apply`` then ``dvc repro`` makes it for a chosen run).

Each experiment is named ``<configuration>-seed<k>`` and sets every switch it relies on (``-S`` edits the
queued copy's ``params.yaml`` only). DVC runs queued experiments in temporary copies of the project; the MLflow
store and Ray's checkpoints stay in the project (:func:`endoflow.locations.home_project`). One worker at a time
(``-j 1``): the embedded MLflow store is one SQLite file, and one training already uses every core. When the
queue is done, ``endoflow report`` aggregates the runs by configuration over seeds.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Iterable

from endoflow.report import ABLATIONS, DEFAULT_KL_WEIGHT

SWEEP_TARGET = "evaluate"
# The VAE study (docs/method.md): the full model with the warp's sampling or the KL taken away, and beta over
# decades: (name, model.pose_sample, loss.kl_weight). Beside the ablation sweep's full and no-vae runs of the same
# seeds it tells what the VAE contributes.
VAE_STUDY = (("vae-mean-warp", False, DEFAULT_KL_WEIGHT), ("vae-beta0", True, 0.0), ("vae-beta1e-4", True, 1e-4),
             ("vae-beta1e-3", True, 1e-3))
STUDIES = ("ablation", "vae")


class SweepError(RuntimeError):
    """A ``dvc`` command of the sweep failed; DVC has printed why."""


def sweep_commands(seeds: Iterable[int], study: str = "ablation") -> list[list[str]]:
    """The ``dvc`` arguments that queue every configuration of ``study`` (:data:`STUDIES`) with every seed,
    seed by seed."""
    if study not in STUDIES:
        raise ValueError(f"study: expected one of {', '.join(STUDIES)}, got {study!r}")
    if study == "ablation":
        configurations = [(name, {"model.latent_bank": bank, "model.pose_vae": vae}) for name, bank, vae in ABLATIONS]
    else:
        # beta in YAML's float form (1.0e-04): `-S` values are parsed as YAML, where 1e-04 would be a string
        configurations = [(name, {"model.latent_bank": True, "model.pose_vae": True, "model.pose_sample": sample,
                                  "loss.kl_weight": f"{beta:.1e}"}) for name, sample, beta in VAE_STUDY]
    return [["exp", "run", "--queue", "-n", f"{name}-seed{seed}"]
            + [part for key, value in settings.items() for part in ("-S", f"{key}={_yaml(value)}")]
            + ["-S", f"seed={seed}", SWEEP_TARGET]
            for seed in seeds for name, settings in configurations]


def _yaml(value: bool | str) -> str:
    return str(value).lower() if isinstance(value, bool) else value


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
