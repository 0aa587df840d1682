"""DVC stage `pretrain_latent_bank`: SceneNet depth shards -> the pretrained generative latent bank.

Usage: ``python -m stages.pretrain_latent_bank [--params params.yaml]``; logs an MLflow run in
``tracking.latent_bank_experiment``. See docs/method.md, "Generative latent bank".
"""

from __future__ import annotations

import argparse

from endoflow.config import load_params
from endoflow.training.pretrain import pretrain_latent_bank


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    pretrain_latent_bank(
        params,
        shards_dir=params.latent_bank.shards,
        out_path=params.latent_bank.out,
        metrics_path=params.latent_bank.metrics,
        plots_dir=params.latent_bank.plots,
    )


if __name__ == "__main__":
    main()
