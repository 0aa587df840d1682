"""Write dvc.yaml's code deps from the imports: each stage depends on exactly the files it runs.

``python -m tools.dvc_deps`` (``make dvc-deps``) rewrites, in every stage's ``deps``, the paths under ``stages/``
and ``endoflow/`` with the stage's import closure: its script, ``stages/__init__.py`` and every endoflow module
the script imports, directly or not. Everything else in dvc.yaml (data deps with their comments, params, outs,
metrics, plots, comments) stays as it is. ``tests/test_dvc_deps.py`` fails while dvc.yaml is out of date.

Why generated files and not package folders: DVC reruns a stage when a dep changes, and stages import parts of
packages (``train`` reads shards with ``data/loader.py`` but never runs a reader; ``reconstruct`` encodes frames
with ``data/frame_encoding.py`` but never the shard writer), so a folder dep would rerun training for an edit to
a reader. Listing the closure keeps the rule: an edit to a module reruns exactly the stages that import it.

The closure is static (ast over the sources): ``import a.b``, ``from a import b`` where b may be a submodule,
relative imports, imports inside functions (a lazy import still runs) and every package ``__init__.py`` on the
way (Python runs it on import); imports under ``if TYPE_CHECKING:`` never run and are left out. Empty files are
left out too (DVC warns about an empty dep on every run, and an empty file changes nothing).
"""

from __future__ import annotations

import ast
import re
import shlex
from pathlib import Path

import yaml

from endoflow.io import write_text

PROJECT = Path(__file__).resolve().parents[1]
PACKAGE = "endoflow"
CODE_ROOTS = (f"{PACKAGE}/", "stages/")
COMMAND = "make dvc-deps"  # what a failing check tells the user to run


# ------------------------------------------------------------------------------------------- the import closure
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
    """How the script reaches `path`, for a message: `script -> module -> ... -> path`."""
    chain = [path]
    while closure[chain[-1]] is not None:
        chain.append(closure[chain[-1]])
    return " -> ".join(reversed(chain))


# ------------------------------------------------------------------------------------------------ the stages
def dvc_stages(text: str) -> dict[str, dict]:
    """Each stage of dvc.yaml's text by name; a `foreach` stage is its `do` template, whose cmd and code deps are
    the same for every item."""
    stages = yaml.safe_load(text)["stages"]
    return {name: body["do"] if "foreach" in body else body for name, body in stages.items()}


def stage_script(stage: dict) -> str:
    """The file of the one module the stage's cmd runs (`python -m stages.<name> ...`), relative to the project."""
    words = shlex.split(stage["cmd"])
    if words[:2] != ["python", "-m"] or not words[2].startswith("stages."):
        raise ValueError(f"cmd {stage['cmd']!r} should run one module of stages/ from the project root: "
                         f"python -m stages.<name>")
    return words[2].replace(".", "/") + ".py"


def is_code_path(dep: str) -> bool:
    """A dep that is a path of the project's code (templated deps, `${...}`, are data)."""
    return "${" not in dep and dep.startswith(CODE_ROOTS)


def stage_code_deps(closure: dict[str, str | None], root: Path) -> list[str]:
    """The code deps a stage with this import closure needs: its files, those of stages/ first, each group sorted;
    empty ones left out."""
    return sorted((path for path in closure if (root / path).stat().st_size > 0),
                  key=lambda path: (not path.startswith("stages/"), path))


def closures(text: str, root: Path) -> dict[str, dict[str, str | None]]:
    """Each stage's import closure."""
    return {name: import_closure(root / stage_script(stage), root) for name, stage in dvc_stages(text).items()}


# ------------------------------------------------------------------------------------------ rewriting the text
def rewrite_deps(text: str, root: Path) -> str:
    """dvc.yaml's text with every stage's code deps replaced by its import closure, the rest unchanged."""
    wanted = {name: stage_code_deps(closure, root) for name, closure in closures(text, root).items()}
    lines = text.split("\n")
    out: list[str] = []
    stage = None
    i = 0
    while i < len(lines):
        line = lines[i]
        match = re.fullmatch(r"  ([\w@-]+):\s*", line)
        if match and _inside_stages(lines, i):
            stage = match.group(1)
        out.append(line)
        i += 1
        if stage in wanted and re.fullmatch(r"\s+deps:\s*", line):
            block_end = _block_end(lines, i, _indent(line))
            out += _rewritten_block(lines[i:block_end], wanted[stage], _indent(line) + 2)
            i = block_end
    return "\n".join(out)


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _inside_stages(lines: list[str], index: int) -> bool:
    """Whether line `index` (indented two spaces) is under the top-level `stages:` key."""
    for line in reversed(lines[:index]):
        if line and not line.startswith((" ", "#")):
            return line.rstrip() == "stages:"
    return False


def _block_end(lines: list[str], start: int, key_indent: int) -> int:
    """The index after the list under a key indented `key_indent`: the first line indented no deeper than it."""
    end = start
    while end < len(lines) and lines[end].strip() and _indent(lines[end]) > key_indent:
        end += 1
    return end


def _rewritten_block(block: list[str], code: list[str], indent: int) -> list[str]:
    """The deps list with `code` first, then every other entry with the comments above it; the comments above a
    code dep go with it (they described a hand-kept list)."""
    kept, comments = [], []
    for line in block:
        if line.lstrip().startswith("#"):
            comments.append(line)
            continue
        item = line.strip()[2:] if line.strip().startswith("- ") else None
        if item is None or not is_code_path(item.rstrip(":").strip("'\"")):
            kept += comments + [line]
        comments = []
    return [" " * indent + f"- {path}" for path in code] + kept + comments


def main() -> None:
    dvc_yaml = PROJECT / "dvc.yaml"
    text = dvc_yaml.read_text()
    new = rewrite_deps(text, PROJECT)
    if new == text:
        print("dvc.yaml: every stage's code deps are its imports already")
        return
    write_text(dvc_yaml, new)
    print("dvc.yaml: code deps written from the imports")
    before, after = dvc_stages(text), dvc_stages(new)
    for name in after:
        old, now = set(_code_deps(before.get(name, {}))), set(_code_deps(after[name]))
        if old != now:
            print(f"  {name}: added {sorted(now - old)}, removed {sorted(old - now)}")


def _code_deps(stage: dict) -> list[str]:
    return [dep for dep in stage.get("deps", []) if isinstance(dep, str) and is_code_path(dep)]


if __name__ == "__main__":
    main()
