"""DVC stage `reconstruct` (foreach sequence): a built-in test sequence reconstructed, measured on its ground truth.

Usage: ``python -m stages.reconstruct NAME`` (a key of ``reconstruct.sequences``); logs into the model's MLflow
run. With ``reconstruct.adapt`` steps the model is first fitted to the sequence's frames, as ``endoflow reconstruct
--adapt`` fits it to a user's video, and used where it explains the held-out frames better. See
docs/reconstruction.md, "Measured on exact ground truth".
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from endoflow.config import load_params
from endoflow.reconstruction.measure import format_measurement, run_reconstruction, stage_model_file
from endoflow.reconstruction.reconstruct import ADAPTED_MODEL, Adaptation
from endoflow.training.adapt import adapt_to_reconstruct_sequence, fits_better


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name", help="a key of reconstruct.sequences")
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    with stage_model_file(params) as model_path, tempfile.TemporaryDirectory() as scratch:
        adaptation = None
        if params.reconstruct.adapt > 0:
            adapted = Path(scratch) / ADAPTED_MODEL
            fit = adapt_to_reconstruct_sequence(params, args.name, model_path, adapted)
            adaptation = Adaptation.of(adapted, fit, fits_better(fit))
        result = run_reconstruction(params, args.name, model_path, adaptation=adaptation)
    print(format_measurement(args.name, result), end="")


if __name__ == "__main__":
    main()
