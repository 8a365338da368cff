"""The package layout, as rules read from every module's imports (``ast``), not as a list of folders.

- Layers: ``psfmt`` imports neither ``pstoolkit`` nor a plugin; ``pstoolkit`` imports no plugin.
- Inside ``pstoolkit`` the subpackages (and the root modules) stand in ``LAYERS``, lowest first: a
  module imports its own subpackage or a lower one, never a higher one.
- No circle of imports between the modules of ``psfmt``, of ``pstoolkit`` or of a plugin.
- No re-export for an old path: a module other than a package's ``__init__`` imports no name it
  does not use, nobody imports a name from a module that only imported it itself, and nothing
  rewrites ``sys.modules`` or installs an import finder.
- Nothing heavy (torch, numba, matplotlib) loads with the packages, the CLI or the light modules.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import pytest
from helpers import REPO

ROOT = REPO
PLUGINS = sorted(p.name for p in (REPO / "plugins").iterdir() if (p / "__init__.py").exists())
LAYERS = (
    "errors", "version", "_shared", "grid", "plugin", "io", "optics", "events", "evaluation", "surface", "shadows", "solve",
    "hardware", "sim", "view", "", "cli", "testing",
)  # fmt: skip
"""pstoolkit's parts, lowest first; "" is the package root (``pstoolkit/__init__.py``), which
gathers what a plugin needs from the parts below it."""


@dataclass
class Module:
    name: str
    path: Path
    tree: ast.Module
    imports: list[tuple[str, int]] = field(default_factory=list)
    """(imported module, line) of every import outside ``if TYPE_CHECKING``, deferred ones too."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO / "plugins" if path.is_relative_to(REPO / "plugins") else REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _runtime_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node but those under ``if TYPE_CHECKING:``."""
    out: list[ast.AST] = []
    stack = [tree]
    while stack:
        node = stack.pop()
        out.append(node)
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and isinstance(child.test, ast.Name) and child.test.id == "TYPE_CHECKING":
                stack.extend(child.orelse)
                continue
            stack.append(child)
    return out


@cache
def modules() -> dict[str, Module]:
    found: dict[str, Module] = {}
    paths = [*(REPO / "psfmt").rglob("*.py"), *(REPO / "pstoolkit").rglob("*.py"), *(REPO / "plugins").rglob("*.py")]
    for path in sorted(paths):
        module = Module(_module_name(path), path, ast.parse(path.read_text(encoding="utf-8")))
        found[module.name] = module
    for module in found.values():
        package = module.name if module.path.name == "__init__.py" else module.name.rpartition(".")[0]
        for node in _runtime_nodes(module.tree):
            if isinstance(node, ast.Import):
                module.imports += [(alias.name, node.lineno) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    module.imports.append((sub if sub in found else base, node.lineno))
    return found


def _top(name: str) -> str:
    return name.split(".")[0]


def _part(name: str) -> str:
    """The part of pstoolkit a module belongs to: its subpackage, root module or "" for the root."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_psfmt_imports_no_pstoolkit_and_pstoolkit_no_plugin() -> None:
    wrong = [
        f"{m.path.relative_to(REPO)}:{line} imports {target}"
        for m in modules().values()
        for target, line in m.imports
        if (_top(m.name) == "psfmt" and _top(target) in {"pstoolkit", *PLUGINS})
        or (_top(m.name) == "pstoolkit" and _top(target) in PLUGINS)
    ]
    assert wrong == []


def test_every_part_of_pstoolkit_stands_in_the_layers() -> None:
    parts = {_part(name) for name in modules() if _top(name) == "pstoolkit"}
    assert sorted(parts - set(LAYERS)) == []


def test_no_import_runs_up_the_layers_of_pstoolkit() -> None:
    rank = {part: i for i, part in enumerate(LAYERS)}
    wrong = [
        f"{m.path.relative_to(REPO)}:{line}: {_part(m.name) or 'pstoolkit'} imports {target} ({_part(target) or 'pstoolkit'} is above it)"
        for m in modules().values()
        if _top(m.name) == "pstoolkit"
        for target, line in m.imports
        if _top(target) == "pstoolkit" and _part(target) != _part(m.name) and rank[_part(target)] > rank[_part(m.name)]
    ]
    assert wrong == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_circle_of_imports_between_modules() -> None:
    """A package's ``__init__`` is left out: it imports its modules to export them, and a module
    importing a sibling through the package is what the first import of the package does anyway."""
    found = modules()
    graph = {
        name: {t for t, _ in m.imports if t in found and t != name and found[t].path.name != "__init__.py"}
        for name, m in found.items()
        if m.path.name != "__init__.py"
    }
    assert _cycles(graph) == []


def _used_names(tree: ast.Module) -> set[str]:
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            used.update(node.value.replace("[", " ").replace("]", " ").replace(",", " ").replace("|", " ").split())  # string annotations
    return used


def test_no_module_re_exports_a_name_for_another_path() -> None:
    found = modules()
    unused, through = [], []
    for m in found.values():
        if m.path.name == "__init__.py":
            continue
        used = _used_names(m.tree)
        for node in m.tree.body:
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                unused += [f"{m.path.relative_to(REPO)}:{node.lineno} imports {a.name} unused" for a in node.names if (a.asname or a.name) not in used]
    importers = {m.path: m.tree for m in found.values()}
    importers |= {path: ast.parse(path.read_text(encoding="utf-8")) for folder in ("tests", "benchmarks", "examples") for path in (REPO / folder).rglob("*.py")}
    for path, tree in sorted(importers.items()):
        for node in ast.walk(tree):
            if not (isinstance(node, ast.ImportFrom) and node.module in found and found[node.module].path.name != "__init__.py"):
                continue
            source = found[node.module].tree
            defined = {n.name for n in source.body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)}
            targets = [t for n in source.body if isinstance(n, ast.Assign) for t in n.targets]
            targets += [n.target for n in source.body if isinstance(n, ast.AnnAssign)]
            defined |= {t.id for target in targets for t in ast.walk(target) if isinstance(t, ast.Name)}
            imported = {a.asname or a.name for n in source.body if isinstance(n, ast.ImportFrom) for a in n.names}
            through += [
                f"{path.relative_to(REPO)}:{node.lineno} takes {a.name} from {node.module}, which imports it"
                for a in node.names
                if a.name in imported - defined and f"{node.module}.{a.name}" not in found
            ]
    assert (unused, through) == ([], [])


def test_nothing_rewrites_the_import_system() -> None:
    wrong = []
    for m in modules().values():
        for node in ast.walk(m.tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "sys" and node.attr == "meta_path":
                wrong.append(f"{m.path.relative_to(REPO)}:{node.lineno} uses sys.meta_path")
            if isinstance(node, ast.Assign | ast.AugAssign):
                for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    text = ast.unparse(target)
                    if text.startswith("sys.modules") or text.endswith(".__class__"):
                        wrong.append(f"{m.path.relative_to(REPO)}:{node.lineno} assigns {text}")
    assert wrong == []


def test_pstoolkit_exports_what_a_plugin_needs() -> None:
    import pstoolkit
    from pstoolkit._shared.progress import Progress
    from pstoolkit.optics.brdf import BRDF

    assert pstoolkit.BRDF is BRDF and pstoolkit.Progress is Progress
    missing = [name for name in pstoolkit.__all__ if not hasattr(pstoolkit, name)]
    assert missing == []
    with pytest.raises(AttributeError, match="has no attribute 'nothing'"):
        pstoolkit.nothing  # noqa: B018


def test_the_packages_the_cli_and_the_light_modules_load_neither_torch_nor_numba() -> None:
    packages = sorted(name for name, m in modules().items() if m.path.name == "__init__.py" and _top(name) in {"psfmt", "pstoolkit"})
    packages += ["pstoolkit.grid", "pstoolkit.sim.timing", "pstoolkit.sim.exposure", "pstoolkit_diligent.converters"]
    code = f"import sys\nfor p in {packages!r}: __import__(p)\nprint(sorted({{'torch', 'numba', 'matplotlib'}} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_ruff_finds_nothing_with_the_configured_rules() -> None:
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (pip install -e '.[test]')")
    done = subprocess.run([ruff, "check", "--no-cache", str(ROOT)], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:]
