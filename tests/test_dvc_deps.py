"""dvc.yaml knows what each stage runs: every stage's deps cover exactly the project files its script runs, so an
edit to a module reruns exactly the stages that import it and no other.

The deps are written from the imports by `make dvc-deps` (`tools/dvc_deps.py`, which says how the closure is found
and why files rather than package folders); while dvc.yaml is out of date these tests fail and name that command.
"""

from __future__ import annotations

import difflib
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tools.dvc_deps import (
    COMMAND,
    PACKAGE,
    PROJECT,
    closures,
    dvc_stages,
    import_chain,
    import_closure,
    is_code_path,
    rewrite_deps,
)

TEXT = (PROJECT / "dvc.yaml").read_text()
STAGES = dvc_stages(TEXT)
RUN = f"run `{COMMAND}` (python -m tools.dvc_deps) to write every stage's code deps from its imports"


def code_deps(stage: dict) -> list[str]:
    """The stage's deps that are paths of the project's code (templated deps, `${...}`, are data)."""
    paths = [next(iter(dep)) if isinstance(dep, dict) else dep for dep in stage.get("deps", [])]
    return [path.rstrip("/") for path in paths if is_code_path(path)]


def project_code_files() -> list[str]:
    """Every Python file of the library and the stage scripts, relative to the project."""
    files = [*(PROJECT / PACKAGE).rglob("*.py"), *(PROJECT / "stages").glob("*.py")]
    return sorted(path.relative_to(PROJECT).as_posix() for path in files)


def covers(dep: str, path: str) -> bool:
    return path == dep or path.startswith(dep + "/")


@pytest.fixture(scope="module", params=sorted(STAGES))
def stage(request: pytest.FixtureRequest) -> tuple[str, dict, dict[str, str | None]]:
    name = request.param
    return name, STAGES[name], closures(TEXT, PROJECT)[name]


def test_dvc_yaml_lists_the_code_deps_that_the_imports_give() -> None:
    """A new import, module or stage changes what a stage runs: dvc.yaml must say so before DVC can rerun it."""
    written = rewrite_deps(TEXT, PROJECT)
    change = list(difflib.unified_diff(TEXT.splitlines(), written.splitlines(), "dvc.yaml", "imports", lineterm=""))
    assert written == TEXT, f"dvc.yaml's code deps are not the stages' imports: {RUN}\n" + "\n".join(change[:40])


def test_each_stage_s_deps_cover_exactly_the_files_it_runs(stage: tuple) -> None:
    """The guarantee: editing a file the stage runs changes one of its deps (else `dvc repro` would keep a stale
    output), and editing any other file changes none (else DVC would rerun the stage for nothing)."""
    name, body, closure = stage
    deps = code_deps(body)
    covered = {path for path in project_code_files() if any(covers(dep, path) for dep in deps)}
    runs = {path for path in closure if (PROJECT / path).stat().st_size > 0}  # an empty file changes nothing
    missing = [f"  {path}   ({import_chain(closure, path)})" for path in sorted(runs - covered)]
    needless = [f"  {path}" for path in sorted(covered - runs)]
    problems = ([f"stage {name}: dvc.yaml deps miss files it runs:"] + missing if missing else []) + (
        [f"stage {name}: dvc.yaml deps cover files it never runs:"] + needless if needless else [])
    assert not problems, "\n".join(problems + [RUN])


def test_every_code_dep_of_a_stage_is_a_file_that_exists(stage: tuple) -> None:
    """DVC hashes every file in a directory dep, `__pycache__` included (unless .dvcignore names it), and a dep
    naming a file that is gone (renamed, moved) tracks nothing."""
    name, body, _ = stage
    wrong = [dep for dep in code_deps(body) if not (PROJECT / dep).is_file()]
    assert not wrong, f"stage {name}: dvc.yaml deps that are not files: {wrong}; {RUN}"


def test_no_code_dep_of_a_stage_is_an_empty_file(stage: tuple) -> None:
    """DVC prints a warning for every empty dep on every `dvc repro` (an empty package `__init__.py`, say)."""
    name, body, _ = stage
    empty = [dep for dep in code_deps(body) if (PROJECT / dep).is_file() and (PROJECT / dep).stat().st_size == 0]
    assert not empty, f"stage {name}: dvc.yaml deps name empty files, which DVC warns about: {empty}; {RUN}"


def test_the_closure_of_preprocess_holds_the_handedness_conversion() -> None:
    """Preprocessing converts SimCol's left-handed poses with geometry/pose.py, reached only through the readers,
    so the closure must find it."""
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


SMALL_PROJECT = {
    "stages/__init__.py": '"""stages"""\n',
    "stages/a.py": "from endoflow import m\n",
    "endoflow/__init__.py": '"""the package"""\n',
    "endoflow/m.py": "import endoflow.n\nimport endoflow.empty\n",
    "endoflow/n.py": "x = 1\n",
    "endoflow/empty.py": "",
    "endoflow/unused.py": "y = 1\n",
}
BEFORE = """\
# the pipeline
stages:
  a:
    foreach: [x, y]
    do:
      cmd: python -m stages.a ${item}
      deps:
        # why a hand-kept dep was there
        - endoflow/unused.py
        - stages/a.py
        # the data it reads
        - ${item}
      outs:
        - out/${item}
plots:
  - endoflow/unused.py:
      x: epoch
"""
AFTER = """\
# the pipeline
stages:
  a:
    foreach: [x, y]
    do:
      cmd: python -m stages.a ${item}
      deps:
        - stages/__init__.py
        - stages/a.py
        - endoflow/__init__.py
        - endoflow/m.py
        - endoflow/n.py
        # the data it reads
        - ${item}
      outs:
        - out/${item}
plots:
  - endoflow/unused.py:
      x: epoch
"""


def test_the_rewrite_lists_each_stage_s_files_and_keeps_everything_else(tmp_path: Path) -> None:
    """Code deps become the closure (the stage's package first, empty files left out, a module it never imports
    dropped with the comment above it); data deps keep their comments; the rest of the file is untouched; a
    second rewrite changes nothing."""
    write_files(tmp_path, SMALL_PROJECT)
    assert rewrite_deps(BEFORE, tmp_path) == AFTER
    assert rewrite_deps(AFTER, tmp_path) == AFTER


def test_a_stage_run_in_a_copy_of_the_project_imports_the_copys_library(tmp_path: Path):
    """DVC runs a queued experiment in a copy of the project: the copy's library must run, not the environment's
    editable install (the workspace's files), or an experiment queued with a change to the library would not run
    the change."""
    shutil.copytree(PROJECT / "stages", tmp_path / "stages", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / PACKAGE).mkdir()
    (tmp_path / PACKAGE / "__init__.py").write_text("raise ImportError('the library of the copy')\n")
    for name, stage in STAGES.items():
        command = [sys.executable] + [word for word in shlex.split(stage["cmd"])[1:] if "${" not in word]
        result = subprocess.run(command + ["--help"], cwd=tmp_path, capture_output=True, text=True)
        assert "the library of the copy" in result.stderr, f"{name}: {result.stderr[-500:]}"
