"""The layer picture of docs/architecture.md, checked on the imports: lower layers never import higher ones, and no
module imports itself through others (a circle of imports has no lowest module to read first)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "endoflow"

# endoflow's packages and modules: io.py, the lowest layer with config.py, imports only the errors every layer raises
TOP_LEVEL = sorted(f"endoflow.{path.stem if path.is_file() else path.name}" for path in PACKAGE.iterdir()
                   if (path.suffix == ".py" and path.stem != "__init__") or (path / "__init__.py").is_file())

# Preprocessing's writer: its entry points, plan, staging, engines and the writing of one shard.
SHARD_WRITING = ["endoflow.data.shards", "endoflow.data.shard_plan", "endoflow.data.shard_staging",
                 "endoflow.data.shard_engines", "endoflow.data.shard_writer"]

# module prefix -> endoflow modules it must not import (directly, at any place in the file)
FORBIDDEN = {
    "endoflow.errors": ["endoflow."],
    "endoflow.io": [module for module in TOP_LEVEL if module != "endoflow.errors"],
    "endoflow.config": ["endoflow."],
    "endoflow.locations": ["endoflow."],
    "endoflow.progress": ["endoflow."],
    "endoflow.shapes": ["endoflow."],
    "endoflow.compiled": ["endoflow."],
    "endoflow.ray_worker_setup": ["endoflow."],  # run first in every Ray worker process: nothing it need not load
    "endoflow.ray_runtime": ["endoflow.data", "endoflow.models", "endoflow.training", "endoflow.evaluation",
                             "endoflow.synth"],
    "endoflow.synth": ["endoflow.models", "endoflow.training", "endoflow.evaluation"],
    "endoflow.geometry": ["endoflow.data", "endoflow.models", "endoflow.losses", "endoflow.training",
                          "endoflow.evaluation", "endoflow.synth", "endoflow.reconstruction"],
    "endoflow.losses": ["endoflow.data", "endoflow.models", "endoflow.training", "endoflow.evaluation"],
    "endoflow.data": ["endoflow.models", "endoflow.training", "endoflow.evaluation", "endoflow.reconstruction"],
    "endoflow.data.frame_encoding": ["endoflow.data."],
    "endoflow.data.shard_format": [*SHARD_WRITING, "endoflow.data.loader", "endoflow.data.registry",
                                   "endoflow.data.simcol", "endoflow.data.endoslam", "endoflow.data.scenenet"],
    "endoflow.data.loader": [*SHARD_WRITING, "endoflow.data.registry", "endoflow.data.simcol",
                             "endoflow.data.endoslam", "endoflow.data.scenenet"],
    # the sequence reader reads as the triplet reader does, through it
    "endoflow.data.sequences": [*SHARD_WRITING, "endoflow.data.registry", "endoflow.data.simcol",
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


def import_graph() -> dict[str, set[str]]:
    """Each endoflow module -> the endoflow modules it imports (anywhere in the file: a lazy import still runs)."""
    paths = {module_name(path): path for path in PACKAGE.rglob("*.py")}
    return {name: imported_modules(path) & set(paths) - {name} for name, path in paths.items()}


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import one another round a circle (strongly connected, more than one module)."""
    order, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(module: str) -> None:
        order[module] = low[module] = len(order)
        stack.append(module)
        on_stack.add(module)
        for imported in sorted(graph[module]):
            if imported not in order:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], order[imported])
        if low[module] == order[module]:
            group = []
            while not group or group[-1] != module:
                group.append(stack.pop())
                on_stack.discard(group[-1])
            if len(group) > 1:
                circles.append(sorted(group))

    for module in sorted(graph):
        if module not in order:
            visit(module)
    return circles


def test_no_modules_import_one_another_in_a_circle() -> None:
    circles = import_circles(import_graph())
    assert not circles, "modules that import one another in a circle (move what both need to a lower module):\n" + \
        "\n".join("  " + ", ".join(group) for group in circles)


def test_a_circle_of_imports_is_found() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert import_circles(graph) == [["a", "b", "c"]]


# libraries of about a second or more each to import on 2 cores (torch 3.4 s, mlflow 2.8 s, pandas 0.9 s)
HEAVY_LIBRARIES = ("torch", "mlflow", "ray", "matplotlib", "pandas", "kornia", "webdataset")


def test_the_command_line_loads_without_the_heavy_libraries() -> None:
    """`endoflow --help` and a mistyped option answer at once: each command imports what it runs when it runs
    (a reader's name list that came with torch made `endoflow --help` take about 4 s instead of under 1)."""
    script = ("import sys, endoflow.cli; "
              f"print(' '.join(name for name in {HEAVY_LIBRARIES!r} if name in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                            cwd=PACKAGE.parent).stdout.split()
    assert loaded == [], f"importing endoflow.cli loads {loaded}"


def test_a_training_worker_loads_mlflow_and_matplotlib_only_to_log() -> None:
    """Every Ray Train worker imports the training loop; only rank 0 logs to MLflow and draws the validation frames,
    so the others do without both (about 2.5 s of CPU in every worker on 2 cores)."""
    script = ("import sys, endoflow.training.loop; "
              "print(' '.join(name for name in ('mlflow', 'matplotlib') if name in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                            cwd=PACKAGE.parent).stdout.split()
    assert loaded == [], f"importing endoflow.training.loop loads {loaded}"
