"""dvc.yaml knows what each stage runs: every stage's `deps` cover exactly the endoflow modules its script imports.

DVC reruns a stage only when one of its deps changed, so a module the stage imports but does not list (the
handedness conversion in `geometry/pose.py` under `preprocess`, say) can change without `dvc repro` noticing,
and a dep the stage never imports reruns it needlessly. Deps are files, not directories (DVC would hash
__pycache__ too). The closure is computed statically (ast over the sources): `import a.b`, `from a import b`
where b may be a submodule, relative imports, imports inside functions (a lazy import still runs), and every
package `__init__.py` on the way (Python executes it on import); imports under `if TYPE_CHECKING:` never run and
are left out. Templated deps (`${...}`) are data paths and are skipped here.
"""

from __future__ import annotations

import ast
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

PROJECT = Path(__file__).resolve().parents[1]
PACKAGE = "endoflow"
CODE_ROOTS = (f"{PACKAGE}/", "stages/")


def dvc_stages() -> dict[str, dict]:
    """Each stage of dvc.yaml by name; a `foreach` stage is its `do` template, whose cmd and code deps are the
    same for every item."""
    stages = yaml.safe_load((PROJECT / "dvc.yaml").read_text())["stages"]
    return {name: body["do"] if "foreach" in body else body for name, body in stages.items()}


def stage_script(stage: dict) -> str:
    """The file of the one module the stage's cmd runs (`python -m stages.<name> ...`), relative to the project."""
    words = shlex.split(stage["cmd"])
    assert words[:2] == ["python", "-m"] and words[2].startswith("stages."), \
        f"cmd {stage['cmd']!r} should run one module of stages/ from the project root: python -m stages.<name>"
    return words[2].replace(".", "/") + ".py"


def code_deps(stage: dict) -> list[str]:
    """The stage's deps that are paths in the project: templated ones (`${...}`) are data and left out."""
    paths = [next(iter(dep)) if isinstance(dep, dict) else dep for dep in stage.get("deps", [])]
    return [path.rstrip("/") for path in paths if "${" not in path]


def module_path(name: str, root: Path) -> Path | None:
    """The file that defines module `name` under `root` (a module file or a package's `__init__.py`), if any."""
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def with_parents(name: str) -> list[str]:
    """`a.b.c` -> `a`, `a.b`, `a.b.c`: importing a module first imports every package above it."""
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def is_type_checking_block(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def runtime_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node of `tree` that can run, at import or in a function: all but the bodies of `if TYPE_CHECKING:`."""
    nodes, todo = [], [tree]
    while todo:
        node = todo.pop()
        nodes.append(node)
        if is_type_checking_block(node):
            todo.extend(node.orelse)
        else:
            todo.extend(ast.iter_child_nodes(node))
    return nodes


def absolute_from(node: ast.ImportFrom, importer: str, importer_is_package: bool) -> str:
    """The absolute module a `from ... import` names, resolving `from .x` against the importing module."""
    if node.level == 0:
        return node.module or ""
    package = importer.split(".") if importer_is_package else importer.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imported_names(path: Path, root: Path) -> list[str]:
    """Module names the file at `path` imports, each with the packages above it; `from m import n` also names
    `m.n`, which is a module when n is a submodule (names that are not modules are dropped by the caller)."""
    importer = module_name(path, root) if path.is_relative_to(root / PACKAGE) else ""
    is_package = path.name == "__init__.py"
    names = []
    for node in runtime_nodes(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names += [parent for alias in node.names for parent in with_parents(alias.name)]
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            module = absolute_from(node, importer, is_package)
            names += with_parents(module) + [f"{module}.{alias.name}" for alias in node.names if alias.name != "*"]
    return names


def import_closure(script: Path, root: Path) -> dict[str, str | None]:
    """Every file run when `script` runs as a module, among the script itself, its package's `__init__.py` and the
    modules of `root/endoflow`, each mapped to the file that first imports it (None for the script), relative to
    `root`."""
    start = script.relative_to(root).as_posix()
    imported_by: dict[str, str | None] = {start: None}
    package = script.parent / "__init__.py"  # `python -m stages.x` runs the package's __init__ first
    if package.is_file():
        imported_by[package.relative_to(root).as_posix()] = start
    todo = [script]
    while todo:
        path = todo.pop(0)
        for name in imported_names(path, root):
            target = module_path(name, root) if name.split(".")[0] == PACKAGE else None
            key = target.relative_to(root).as_posix() if target else None
            if key and key not in imported_by:
                imported_by[key] = path.relative_to(root).as_posix()
                todo.append(target)
    return imported_by


def import_chain(closure: dict[str, str | None], path: str) -> str:
    """How the script reaches `path`, for a failure message: `script -> module -> ... -> path`."""
    chain = [path]
    while closure[chain[-1]] is not None:
        chain.append(closure[chain[-1]])
    return " -> ".join(reversed(chain))


def covers(dep: str, path: str) -> bool:
    return path == dep or path.startswith(dep + "/")


STAGES = dvc_stages()


@pytest.fixture(scope="module", params=sorted(STAGES))
def stage(request: pytest.FixtureRequest) -> tuple[str, dict, dict[str, str | None]]:
    name = request.param
    body = STAGES[name]
    return name, body, import_closure(PROJECT / stage_script(body), PROJECT)


def test_every_module_a_stage_runs_is_one_of_its_deps(stage: tuple) -> None:
    """The stage script itself and every endoflow module it imports, directly or not, is covered by a dep (the
    file, or a directory holding it): otherwise editing it leaves `dvc status` saying nothing changed."""
    name, body, closure = stage
    deps = code_deps(body)
    uncovered = [path for path in closure if not any(covers(dep, path) for dep in deps)]
    assert not uncovered, f"stage {name}: dvc.yaml deps miss modules it runs:\n" + "\n".join(
        f"  {path}   ({import_chain(closure, path)})" for path in uncovered)


def test_every_code_dep_of_a_stage_exists(stage: tuple) -> None:
    """A dep naming a module or script that is gone (renamed, moved) no longer tracks anything."""
    name, body, _ = stage
    stale = [dep for dep in code_deps(body) if dep.startswith(CODE_ROOTS) and not (PROJECT / dep).exists()]
    assert not stale, f"stage {name}: dvc.yaml deps name paths that do not exist: {stale}"


def test_every_code_dep_of_a_stage_is_a_file_not_a_directory(stage: tuple) -> None:
    """DVC hashes every file in a directory dep, `__pycache__` included (it ignores .gitignore), so running any
    module of it would mark the stage changed; and a package listed whole reruns the stage for modules it never
    runs."""
    name, body, _ = stage
    directories = [dep for dep in code_deps(body) if dep.startswith(CODE_ROOTS) and (PROJECT / dep).is_dir()]
    assert not directories, f"stage {name}: dvc.yaml deps name directories, list the files the stage runs " \
                            f"instead: {directories}"


def test_no_code_dep_of_a_stage_is_an_empty_file(stage: tuple) -> None:
    """DVC prints a warning for every empty dep on every `dvc repro` (an empty package `__init__.py`, say)."""
    name, body, _ = stage
    empty = [dep for dep in code_deps(body) if (PROJECT / dep).is_file() and (PROJECT / dep).stat().st_size == 0]
    assert not empty, f"stage {name}: dvc.yaml deps name empty files, which DVC warns about: {empty}"


def test_no_code_dep_of_a_stage_is_a_module_it_never_runs(stage: tuple) -> None:
    """A dep the stage never imports makes DVC rerun it needlessly when that module changes."""
    name, body, closure = stage
    unused = [dep for dep in code_deps(body)
              if dep.startswith(CODE_ROOTS) and (PROJECT / dep).is_file() and dep not in closure]
    assert not unused, f"stage {name}: dvc.yaml deps name modules the stage never imports: {unused}"


def test_the_closure_of_preprocess_holds_the_handedness_conversion() -> None:
    """The issue's example: preprocessing converts SimCol's left-handed poses with geometry/pose.py, reached only
    through the readers, so the closure must find it (test_every_module_a_stage_runs_is_one_of_its_deps then
    requires it as a dep)."""
    closure = import_closure(PROJECT / "stages/preprocess.py", PROJECT)
    assert "endoflow/geometry/pose.py" in closure
    assert "endoflow/geometry/__init__.py" in closure


def write_files(root: Path, files: dict[str, str]) -> None:
    for relative, text in files.items():
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        (root / relative).write_text(text)


def test_the_closure_follows_every_form_of_import_python_runs(tmp_path: Path) -> None:
    """Absolute, `from package import submodule`, relative and in-function imports are followed, package
    `__init__.py` files are included, and imports only a type checker sees, or of other packages, are not."""
    write_files(tmp_path, {
        "run.py": "import os\nfrom endoflow.a import b\n",
        "endoflow/__init__.py": "",
        "endoflow/a/__init__.py": "",
        "endoflow/a/b.py": "from . import c\nfrom .d import name\n",
        "endoflow/a/c.py": "def f():\n    import endoflow.e.f\n",
        "endoflow/a/d.py": "name = 1\n",
        "endoflow/e/__init__.py": "from ..g import thing\n",
        "endoflow/e/f.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from endoflow import h\n",
        "endoflow/g.py": "thing = 2\n",
        "endoflow/h.py": "",
        "endoflow/unused.py": "",
    })
    closure = import_closure(tmp_path / "run.py", tmp_path)
    assert sorted(closure) == ["endoflow/__init__.py", "endoflow/a/__init__.py", "endoflow/a/b.py",
                               "endoflow/a/c.py", "endoflow/a/d.py", "endoflow/e/__init__.py", "endoflow/e/f.py",
                               "endoflow/g.py", "run.py"]
    assert import_chain(closure, "endoflow/g.py") == (
        "run.py -> endoflow/a/b.py -> endoflow/a/c.py -> endoflow/e/__init__.py -> endoflow/g.py")


def test_a_stage_run_in_a_copy_of_the_project_imports_the_copys_library(tmp_path: Path):
    """DVC runs a queued experiment in a copy of the project: the copy's library must run, not the environment's
    editable install (the workspace's files), or an experiment queued with a change to the library would not run
    the change."""
    shutil.copytree(PROJECT / "stages", tmp_path / "stages", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / PACKAGE).mkdir()
    (tmp_path / PACKAGE / "__init__.py").write_text("raise ImportError('the library of the copy')\n")
    for name, stage in dvc_stages().items():
        command = [sys.executable] + [word for word in shlex.split(stage["cmd"])[1:] if "${" not in word]
        result = subprocess.run(command + ["--help"], cwd=tmp_path, capture_output=True, text=True)
        assert "the library of the copy" in result.stderr, f"{name}: {result.stderr[-500:]}"
