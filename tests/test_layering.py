"""The layering of docs/architecture.md, checked by import-linter (contracts in pyproject.toml).

grimp (import-linter's graph builder) walks only the root package's own folder; dualsight's sub-packages live
in top-level folders mapped by ``package-dir`` and linked from ``dualsight/``.  The tests run ``lint-imports``
as a user does, from the repository, and on a copy of the mapped folders as one ``dualsight/`` tree (as a wheel
installs them), where they also plant violations.  grimp reads every import statement, those inside functions
included.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = REPO / "pyproject.toml"
LINT = Path(sys.executable).with_name("lint-imports")

pytestmark = pytest.mark.skipif(not LINT.exists(), reason="import-linter is not installed (pip install -e '.[dev]')")


def merged_tree(dest: Path) -> Path:
    """Copy every folder of pyproject's package-dir mapping to ``dest/<dotted path>`` and return ``dest``."""
    mapping = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-dir"]
    for package, folder in sorted(mapping.items()):
        target = dest.joinpath(*package.split("."))
        shutil.copytree(REPO / folder, target, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return dest


def lint(tree: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT), "--no-cache", "--no-logo", str(PYPROJECT)], cwd=tree, capture_output=True, text=True,
                          env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}, timeout=300)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    return merged_tree(tmp_path_factory.mktemp("merged"))


def test_the_contracts_hold(tree):
    r = lint(tree)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    assert "Contracts: " in r.stdout and " broken" in r.stdout


def test_lint_imports_from_the_repository_sees_every_subpackage():
    """``lint-imports`` run in the repository (what a maintainer types) analyses the whole package through the
    links in ``dualsight/``, not only the root folder's few modules."""
    mapping = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-dir"]
    for package, folder in mapping.items():
        if package != "dualsight":
            link = REPO / "dualsight" / package.split(".", 1)[1]
            assert link.is_symlink() and link.resolve() == (REPO / folder).resolve(), link
    r = lint(REPO)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    code = "import grimp; print(len(grimp.build_graph('dualsight').modules))"
    g = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300,
                       env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert int(g.stdout) == sum(1 for folder in mapping.values() for _ in (REPO / folder).rglob("*.py")), g.stderr


@pytest.mark.parametrize("module, planted, contract", [
    # an import hidden in a function body, from a leaf up to the engine
    ("kernels/rng.py", "def _planted():\n    from dualsight.jobs.engine import runner\n", "kernels-leaf"),
    ("nav/errors.py", "import pyarrow\n", "nav-no-storage"),
    ("warehouse/query.py", "from dualsight.nav import attitude\n", "warehouse-no-algorithm"),
    ("scene/attitude.py", "def _planted():\n    import dualsight.nav.attitude\n", "layers"),
    ("jobs/engine/runner.py", "def _planted():\n    from dualsight.jobs.kinds import star\n", "jobs-layers"),
    ("jobs/kinds/star.py", "def _planted():\n    from dualsight.jobs.cli import args\n", "jobs-layers"),
])
def test_a_planted_violation_breaks_a_contract(tmp_path, module, planted, contract):
    tree = merged_tree(tmp_path)
    path = tree / "dualsight" / module
    path.write_text(path.read_text() + "\n\n" + planted)
    r = lint(tree)
    assert r.returncode != 0
    broken = re.findall(r"^(.+?) BROKEN$", r.stdout, flags=re.M)
    names = {c["id"]: c["name"] for c in tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]}
    assert names[contract] in [b.strip() for b in broken], r.stdout[-3000:]


def documented_layers(table: str) -> list[str]:
    """The second column of a markdown table's body rows, top to bottom, as "a | b" of its `code` names."""
    out = []
    for r in table.splitlines():
        cells = r.split("|")
        if r.startswith("| ") and len(cells) > 3 and "`" in cells[2] and cells[1].strip() != "layer":
            out.append(" | ".join(sorted(re.findall(r"`([\w.]+)`", cells[2]))))
    return out


def test_the_layer_tables_of_the_architecture_page_are_the_contracts():
    """docs/architecture.md's two tables in "Layers" list, top to bottom, the layers of the ``layers`` and
    ``jobs-layers`` contracts."""
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    packages, inside_jobs = section.split("Inside `jobs/`", 1)
    contracts = {c["id"]: c for c in tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]}
    canon = lambda layers: [" | ".join(sorted(x.strip() for x in layer.split("|"))) for layer in layers]
    assert documented_layers(packages) == canon(contracts["layers"]["layers"])
    assert documented_layers(inside_jobs) == canon(contracts["jobs-layers"]["layers"])


def import_cycles(tree: Path) -> list[list[str]]:
    """The strongly connected components (of more than one module) of the package's import graph, every
    import statement counted (those inside functions too), computed by grimp in a subprocess over ``tree``."""
    code = """
import json, sys, grimp
g = grimp.build_graph("dualsight")
adj = {m: sorted(g.find_modules_directly_imported_by(m)) for m in g.modules}
index, low, stack, on, out = {}, {}, [], set(), []
def visit(v):
    index[v] = low[v] = len(index); stack.append(v); on.add(v)
    for w in adj[v]:
        if w not in index:
            visit(w); low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        comp = []
        while True:
            w = stack.pop(); on.discard(w); comp.append(w)
            if w == v:
                break
        if len(comp) > 1:
            out.append(sorted(comp))
sys.setrecursionlimit(100000)
for m in sorted(adj):
    if m not in index:
        visit(m)
print(json.dumps(out))
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=tree, capture_output=True, text=True, timeout=300,
                       env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout)


def test_no_import_cycles(tree):
    """No module reaches itself through imports, not even through an import deferred into a function."""
    assert import_cycles(tree) == []


def test_a_planted_cycle_is_found(tmp_path):
    tree = merged_tree(tmp_path)
    path = tree / "dualsight" / "scene" / "units.py"
    path.write_text(path.read_text() + "\n\ndef _planted():\n    from dualsight.scene import skytruth\n")
    assert any("dualsight.scene.units" in c for c in import_cycles(tree))
