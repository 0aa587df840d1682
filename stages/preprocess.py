"""DVC stage `preprocess` (foreach dataset): native layout -> WebDataset shards + manifest.parquet.

Usage: ``python stages/preprocess.py {simcol,endoslam,scenenet}``; reads ``params.yaml`` and writes
``<preprocess.out>/<dataset>/``. An interrupted run resumes from ``<preprocess.out>/.<dataset>.partial/``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from endoflow.config import load_params
from endoflow.data.base import DATASETS
from endoflow.data.shards import preprocess_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", choices=DATASETS)
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    summary = preprocess_dataset(args.dataset, params, Path(params.preprocess.out) / args.dataset)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
