"""DVC stage `reconstruct` (foreach sequence): a built-in test sequence reconstructed, measured on its ground truth.

Usage: ``python -m stages.reconstruct NAME`` (a key of ``reconstruct.sequences``); logs into the model's MLflow
run. See docs/reconstruction.md, "Measured on exact ground truth".
"""

from __future__ import annotations

import argparse

from endoflow.config import load_params
from endoflow.reconstruction.measure import format_measurement, run_reconstruction


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name", help="a key of reconstruct.sequences")
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    result = run_reconstruction(load_params(args.params), args.name)
    print(format_measurement(args.name, result), end="")


if __name__ == "__main__":
    main()
