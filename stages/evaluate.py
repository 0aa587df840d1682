"""DVC stage `evaluate` (foreach test set): trained model -> metrics, plots and challenge-format predictions.

Usage: ``python -m stages.evaluate TESTSET`` (a key of ``eval.test_sets``); logs into the MLflow run of the
training that produced ``eval.model``. What it writes: docs/outputs.md, "`evaluate@<test set>`".
"""

from __future__ import annotations

import argparse

from endoflow.config import load_params
from endoflow.evaluation.evaluate import run_evaluation
from endoflow.evaluation.summary import format_evaluation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("test_set", help="a key of eval.test_sets")
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    result = run_evaluation(load_params(args.params), args.test_set)
    print(format_evaluation(result), end="")


if __name__ == "__main__":
    main()
