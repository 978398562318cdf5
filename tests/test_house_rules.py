"""House rules of the source tree (docs/architecture.md, "House rules"), checked over the AST of every module.

- No module re-exports a name it does not define: ``from M import n`` must name the module that defines ``n``.
- No ``_private`` name is imported across modules (package code, tests and benchmarks alike).
- An import inside a function defers a heavy module (taichi, pyarrow, astropy, dask, duckdb, matplotlib,
  rerun, cv2, scipy, sep, pandas) or a project module whose top-level imports reach one; every other import
  stands at the top of its module, where a reader (and import-linter) sees the graph at a glance.
"""

from __future__ import annotations

import ast
import functools
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HEAVY = {"taichi", "pyarrow", "astropy", "dask", "distributed", "duckdb", "matplotlib", "rerun", "cv2", "scipy",
         "sep", "pandas"}


def package_modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package-dir mapping in pyproject.toml."""
    mapping = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    out = {}
    for package, folder in mapping.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = path.relative_to(REPO / folder).with_suffix("").parts
            if rel[0] in ("dualsight", "scene", "nav", "kernels", "catalogs", "jobs", "warehouse", "viz") and \
                    (REPO / folder / rel[0]).is_dir() and folder == ".":
                continue
            parts = rel[:-1] if rel[-1] == "__init__" else rel
            out[".".join((package, *parts))] = path
    return out


MODULES = package_modules()
OTHER_FILES = sorted(p for d in ("tests", "benchmarks", "examples") for p in (REPO / d).rglob("*.py"))


@functools.lru_cache(maxsize=None)
def tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def absolute(module: str, node: ast.ImportFrom) -> str:
    """The absolute module an ImportFrom names (relative imports resolved against ``module``)."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    is_pkg = MODULES.get(module, Path()).name == "__init__.py"
    base = base[: len(base) - node.level + (1 if is_pkg else 0)]
    return ".".join(base + ([node.module] if node.module else []))


@functools.lru_cache(maxsize=None)
def defined(module: str) -> frozenset[str]:
    """Names a module binds at top level other than by importing them (defs, classes, assignments)."""
    names = set()
    for node in ast.walk(tree(MODULES[module])):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            for t in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                names.update(n.id for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.For, ast.With)):
            names.update(n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store))
    return frozenset(names)


def from_imports(path: Path, module: str = ""):
    """(line, absolute module, name) of every ``from dualsight... import name`` in a file."""
    for node in ast.walk(tree(path)):
        if isinstance(node, ast.ImportFrom):
            src = absolute(module, node) if module else (node.module or "")
            if src.startswith("dualsight"):
                for a in node.names:
                    yield node.lineno, src, a.name


def all_files():
    yield from ((m, p) for m, p in MODULES.items())
    yield from (("", p) for p in OTHER_FILES)


def test_no_module_reexports_a_name_it_does_not_define():
    bad = []
    for module, path in all_files():
        for line, src, name in from_imports(path, module):
            if src in MODULES and name != "*" and f"{src}.{name}" not in MODULES and name not in defined(src):
                bad.append(f"{path.relative_to(REPO)}:{line}: {name} from {src}, which does not define it")
    for module, path in MODULES.items():
        for node in tree(path).body:
            if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "__all__" for t in node.targets):
                for elt in getattr(node.value, "elts", []):
                    if isinstance(elt, ast.Constant) and elt.value not in defined(module) \
                            and f"{module}.{elt.value}" not in MODULES and module != "dualsight":
                        bad.append(f"{path.relative_to(REPO)}: __all__ lists {elt.value}, not defined there")
    assert not bad, "\n".join(bad)


def test_no_private_name_is_imported_across_modules():
    bad = [f"{path.relative_to(REPO)}:{line}: {name} from {src}"
           for module, path in all_files() for line, src, name in from_imports(path, module)
           if name.startswith("_") and not name.startswith("__") and src != module]
    assert not bad, "\n".join(bad)


@functools.lru_cache(maxsize=None)
def reaches_heavy(module: str, _seen: frozenset = frozenset()) -> bool:
    """Whether importing ``module`` imports a heavy third-party module through top-level imports."""
    if module not in MODULES:
        return module.split(".")[0] in HEAVY
    for node in tree(MODULES[module]).body:
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            src = absolute(module, node)
            targets = [src] + [f"{src}.{a.name}" for a in node.names if f"{src}.{a.name}" in MODULES]
        for t in targets:
            if t.split(".")[0] in HEAVY:
                return True
            if t in MODULES and t not in _seen and t != module and reaches_heavy(t, _seen | {module}):
                return True
    parent = module.rsplit(".", 1)[0]
    return parent != module and parent in MODULES and parent not in _seen and reaches_heavy(parent, _seen | {module})


def guarded_by_import_error(node, parents) -> bool:
    for p in parents:
        if isinstance(p, ast.Try) and any(
                isinstance(h.type, (ast.Name, ast.Tuple)) and
                {"ImportError", "ModuleNotFoundError"} & {n.id for n in ast.walk(h.type) if isinstance(n, ast.Name)}
                for h in p.handlers):
            return True
    return False


def test_imports_inside_functions_only_defer_heavy_modules():
    bad = []
    for module, path in MODULES.items():
        stack = [(tree(path), ())]
        while stack:
            node, parents = stack.pop()
            for child in ast.iter_child_nodes(node):
                stack.append((child, parents + (node,)))
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            if not any(isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef)) for p in parents):
                continue
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                src = absolute(module, node)
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in MODULES else src for a in node.names]
            if guarded_by_import_error(node, parents):
                continue
            light = [t for t in targets if not reaches_heavy(t)]
            if light:
                bad.append(f"{path.relative_to(REPO)}:{node.lineno}: {', '.join(sorted(set(light)))}")
    assert not bad, f"{len(bad)} in-function imports of light modules (move them to the top):\n" + "\n".join(bad)
