"""Code fingerprints: the sha256 of the modules a stage runs, found by following its imports.

A stage's cache key includes the source of its own module and of every `pipeline` module it imports,
directly or not, except the framework around the stages (the engine, the run store, the workspace,
errors, the CLI), whose changes do not change what a stage computes. The config package is keyed:
besides loading, it derives values stages use (the navigator's noise, the jitter horizon, the
windows). A stage's computation is keyed without the visual layer (`exclude`: `pipeline.viz`,
which draws and never computes); its visuals are keyed on their own code. Editing a recording
thus redraws that stage's recording only. A module that computes with data files (a trained
model) names them in a module-level `KEYED_DATA` tuple of paths relative to itself (a folder:
every file in it): their bytes key it as its source does.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
from collections.abc import Iterator
from functools import cache
from pathlib import Path

# Modules that carry no stage behaviour: their edits must not make every run stale.
FRAMEWORK = ("pipeline.errors", "pipeline.engine", "pipeline.io.store", "pipeline.io.files",
             "pipeline.io.transaction", "pipeline.workspace",
             "pipeline.cli")
FRAMEWORK_EXACT = ("pipeline", "pipeline.stages")  # package inits (the stages' registry)


def _is_framework(module: str) -> bool:
    return module in FRAMEWORK_EXACT or any(module == f or module.startswith(f + ".")
                                            for f in FRAMEWORK)


@cache
def _source(module: str) -> tuple[Path, bytes] | None:
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):  # `from pipeline.x import Name`: Name is no module
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    path = Path(spec.origin)
    return path, path.read_bytes()


@cache
def _imports(module: str) -> tuple[str, ...]:
    """`pipeline.*` modules imported by `module` (at any depth of its body)."""
    found = _source(module)
    if found is None:
        return ()
    path, text = found
    is_package = path.name == "__init__.py"
    names: set[str] = set()
    for node in _statements(ast.parse(text)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                parent = ".".join([*base, node.module] if node.module else base)
            else:
                parent = node.module or ""
            names.add(parent)
            names.update(f"{parent}.{a.name}" for a in node.names)
    return tuple(sorted(n for n in names if n.startswith("pipeline") and _source(n)))


def _statements(tree: ast.Module) -> Iterator[ast.stmt]:
    """Every statement of a module, at any depth (imports are statements: expressions, ~90 % of
    the nodes, are not visited)."""
    todo: list[ast.stmt] = list(tree.body)
    while todo:
        node = todo.pop()
        yield node
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            for child in getattr(node, field, ()):
                if isinstance(child, ast.stmt):
                    todo.append(child)
                else:  # an except handler or a match case: its own body
                    todo.extend(child.body)


def _under(module: str, packages: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


@cache
def closure(roots: tuple[str, ...], exclude: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The modules `roots` run: themselves and their `pipeline` imports, less the framework and
    the packages `exclude` (not followed)."""
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(i for i in _imports(m)
                    if (not _is_framework(i) or i in roots) and not _under(i, exclude))
    return tuple(sorted(seen))


@cache
def _keyed_data(module: str) -> bytes:
    """sha256 of the files `module` names in its `KEYED_DATA` (b"" when it names none)."""
    found = _source(module)
    if found is None:
        return b""
    path, text = found
    names: tuple[str, ...] = ()
    for node in ast.parse(text).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "KEYED_DATA"
                                                for t in node.targets):
            names = tuple(ast.literal_eval(node.value))
    if not names:
        return b""
    h = hashlib.sha256()
    for name in names:
        target = (path.parent / name).resolve()
        files = sorted(p for p in target.rglob("*") if p.is_file()) if target.is_dir() \
            else [target] if target.is_file() else []
        for f in files:
            h.update(str(f.relative_to(path.parent.parent)).encode() + b"\0" + f.read_bytes())
    return h.digest()


@cache
def code_hash(roots: tuple[str, ...], exclude: tuple[str, ...] = ()) -> str:
    """sha256 (16 hex) over the names and sources of `closure(roots, exclude)`, and the data
    files they name (`KEYED_DATA`)."""
    h = hashlib.sha256()
    for m in closure(roots, exclude):
        found = _source(m)
        if found is not None:
            h.update(m.encode() + b"\0" + found[1] + b"\0" + _keyed_data(m))
    return h.hexdigest()[:16]
