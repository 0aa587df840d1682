"""DVC stage `preprocess` (foreach dataset): native layout -> WebDataset shards + manifest.parquet.

Usage: ``python -m stages.preprocess {simcol,endoslam,scenenet}``; an interrupted run resumes, and
``preprocess.engine: ray`` writes the shards as Ray tasks. See docs/datasets.md, "Shards", and docs/cluster.md.
"""

from __future__ import annotations

import argparse
import posixpath
from pathlib import Path

from endoflow.config import load_params
from endoflow.data.base import DATASETS
from endoflow.data.shards import format_preprocess_summary, preprocess_dataset
from endoflow.locations import absolute_location


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", choices=DATASETS)
    parser.add_argument("--params", default="params.yaml", help="parameter file (default: params.yaml)")
    args = parser.parse_args()
    params = load_params(args.params)
    out = absolute_location(params.preprocess.out, Path.cwd())
    summary = preprocess_dataset(args.dataset, params, posixpath.join(out.rstrip("/"), args.dataset))
    print(format_preprocess_summary(summary), end="")


if __name__ == "__main__":
    main()
