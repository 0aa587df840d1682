"""The layer picture of docs/architecture.md, checked on the imports: lower layers never import higher ones."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "endoflow"

# Preprocessing's writer: its entry points, plan, staging, engines and the writing of one shard.
SHARD_WRITING = ["endoflow.data.shards", "endoflow.data.shard_plan", "endoflow.data.shard_staging",
                 "endoflow.data.shard_engines", "endoflow.data.shard_writer"]

# module prefix -> endoflow modules it must not import (directly, at any place in the file)
FORBIDDEN = {
    "endoflow.io": ["endoflow."],
    "endoflow.config": ["endoflow."],
    "endoflow.locations": ["endoflow."],
    "endoflow.progress": ["endoflow."],
    "endoflow.shapes": ["endoflow."],
    "endoflow.ray_runtime": ["endoflow.data", "endoflow.models", "endoflow.training", "endoflow.evaluation",
                             "endoflow.synth"],
    "endoflow.synth": ["endoflow.models", "endoflow.training", "endoflow.evaluation"],
    "endoflow.geometry": ["endoflow.data", "endoflow.models", "endoflow.losses", "endoflow.training",
                          "endoflow.evaluation", "endoflow.synth"],
    "endoflow.losses": ["endoflow.data", "endoflow.models", "endoflow.training", "endoflow.evaluation"],
    "endoflow.data": ["endoflow.models", "endoflow.training", "endoflow.evaluation", "endoflow.reconstruction"],
    "endoflow.data.frame_encoding": ["endoflow.data."],
    "endoflow.data.shard_format": [*SHARD_WRITING, "endoflow.data.loader", "endoflow.data.registry",
                                   "endoflow.data.simcol", "endoflow.data.endoslam", "endoflow.data.scenenet"],
    "endoflow.data.loader": [*SHARD_WRITING, "endoflow.data.registry", "endoflow.data.simcol",
                             "endoflow.data.endoslam", "endoflow.data.scenenet"],
    "endoflow.models": ["endoflow.training", "endoflow.evaluation", "endoflow.reconstruction"],
    "endoflow.evaluation": ["endoflow.training", "endoflow.reconstruction"],
    # reconstruction encodes frames as preprocessing does through data.frame_encoding, never the shard writer:
    # a change to how shards are planned or scheduled must not rerun every reconstruction
    "endoflow.reconstruction": ["endoflow.training", *SHARD_WRITING],
    "endoflow.training.pretrain": ["endoflow.evaluation.evaluate", "endoflow.evaluation.plots",
                                   "endoflow.evaluation.metrics"],
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


@pytest.mark.parametrize("path", sorted(PACKAGE.rglob("*.py")), ids=lambda p: module_name(p))
def test_no_module_imports_a_layer_above_it(path: Path) -> None:
    name = module_name(path)
    imports = imported_modules(path)
    for prefix, forbidden in FORBIDDEN.items():
        if name == prefix or name.startswith(prefix + "."):
            wrong = sorted(i for i in imports for f in forbidden if i == f or i.startswith(f.rstrip(".") + "."))
            assert not wrong, f"{name} imports {wrong}, a layer above it (docs/architecture.md)"
