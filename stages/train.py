"""DVC stage `train`: shards + latent bank -> trained model, on Ray Train (DDP), tracked in MLflow.

Usage: ``python -m stages.train [--params params.yaml]``; a rerun after an interruption resumes from the newest
Ray checkpoint in ``ray.storage_path``. See docs/cluster.md and docs/outputs.md, "`train`".
"""

from __future__ import annotations

import argparse
import sys

from endoflow.config import load_params
from endoflow.training.ray_trainer import depth_collapse_warning, format_training_summary, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    summary = train(params)
    print(format_training_summary(summary, params.train.out), end="")
    collapsed = depth_collapse_warning(summary)
    if collapsed:
        print(f"[train] warning: {collapsed}", file=sys.stderr)


if __name__ == "__main__":
    main()
