"""The library's imports point one way: a stated order of layers, no cycle between modules, no reach into another
package's private parts. Read from the source (the AST), so a function-level import counts as much as one at the
top; what runs only as a program (``if __name__ == "__main__":``) or only for type checkers is left out, and so
is ``placejax/__init__.py``, whose re-exports load lazily."""

from __future__ import annotations

import ast
from pathlib import Path

import placejax

ROOT = Path(placejax.__file__).resolve().parent

LAYERS = (
    ("io", "config", "cli", "progress", "evaluation"),  # plumbing every package may use
    ("data",),  # sessions, grid, caches, pipelines
    ("hha", "models"),  # the encoder; the Flax networks
    ("weights", "training", "route"),  # named weights; the training engine; the route filter and matcher
    ("depth",),  # the depth network and its lifecycle
    ("pretrain",),  # the pretrained VGG16 trunk
    ("classify",),  # PlaceClassifier, Tracker: what a robot loads
    ("stages",),  # the method's stages, which write classifiers from runs
)
"""Each package may import packages of earlier layers only (and its own modules)."""


def _module_name(path: Path) -> str:
    parts = ["placejax", *path.relative_to(ROOT).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in ROOT.rglob("*.py")}


def _left_out(node: ast.AST) -> bool:
    """``if __name__ == "__main__":`` and ``if TYPE_CHECKING:`` blocks."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    if isinstance(test, ast.Compare) and isinstance(test.left, ast.Name):
        return test.left.id == "__name__"
    name = test.attr if isinstance(test, ast.Attribute) else getattr(test, "id", "")
    return name.lstrip("_") == "TYPE_CHECKING"


def _imports(name: str) -> list[tuple[str, str | None]]:
    """``(module, imported name or None)`` for every placejax import of module ``name``."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    return _imports_of(path.read_text(encoding="utf-8"), package)


def _imports_of(source: str, package: str) -> list[tuple[str, str | None]]:
    """The imports of ``source`` (a module of ``package``): ``from a import b`` is module ``a.b`` where that is a
    module, else module ``a`` and name ``b``."""
    found: list[tuple[str, str | None]] = []

    def visit(node: ast.AST) -> None:
        if _left_out(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend((alias.name, None) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append((sub, None) if sub in MODULES else (base, alias.name))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(source))
    return [(m, n) for m, n in found if m == "placejax" or m.startswith(("placejax.", "experiments"))]


EDGES = {name: _imports(name) for name in MODULES if name != "placejax"}


def _package(module: str) -> str:
    return module.split(".")[1] if module.count(".") else ""


def test_the_layers_name_every_package_once():
    packages = {_package(m) for m in MODULES if m != "placejax"}
    listed = [p for layer in LAYERS for p in layer]
    assert len(listed) == len(set(listed))
    assert set(listed) == packages, f"unlisted: {packages - set(listed)}, gone: {set(listed) - packages}"


def test_imports_point_down_the_layers():
    layer_of = {p: i for i, layer in enumerate(LAYERS) for p in layer}
    upward = [
        f"{name} imports {module}"
        for name, imports in EDGES.items()
        for module, _ in imports
        if module != "placejax"
        and _package(module) != _package(name)
        and layer_of[_package(module)] >= layer_of[_package(name)]
    ]
    assert not upward, "\n".join(upward)


def test_the_library_never_imports_the_experiments():
    assert not [name for name, imports in EDGES.items() for m, _ in imports if m.startswith("experiments")]


def test_no_cycle_between_modules():
    # Tarjan's strongly connected components over the module graph (the package root left out: lazy).
    graph = {name: {m for m, _ in imports if m in EDGES} for name, imports in EDGES.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    assert not cycles, cycles


def test_no_package_reaches_into_another_packages_private_parts():
    private = [
        f"{name} imports {module}" + (f".{what}" if what else "")
        for name, imports in EDGES.items()
        for module, what in imports
        if _package(module) not in ("", _package(name))
        and (
            any(part.startswith("_") for part in module.split(".")[2:])
            or (what is not None and what.startswith("_") and not what.startswith("__"))
        )
    ]
    assert not private, "\n".join(private)


def test_the_reader_sees_what_the_checks_look_for():
    source = """
import placejax.io
from . import grid
from ..hha import _encode, encode
from typing import TYPE_CHECKING
if TYPE_CHECKING:
    from placejax.stages import Workspace
def f():
    from placejax.route import _lag
if __name__ == "__main__":
    from placejax.data.export import nclt_command
else:
    from placejax.models import vgg
"""
    found = _imports_of(source, "placejax.data")
    assert ("placejax.io", None) in found
    assert ("placejax.data.grid", None) in found  # a module
    assert ("placejax.hha._encode", None) in found
    assert ("placejax.hha", "encode") in found
    assert ("placejax.route._lag", None) in found  # function-level imports count
    assert ("placejax.models", "vgg") in found  # the else branch of a program block counts
    assert not any(m.startswith(("placejax.stages", "placejax.data.export")) for m, _ in found)


# Test modules that exercise the experiments (their commands, configs, reports) or still build their fixture run with
# python -m experiments.cross_season; every other test module tests the library alone.
EXPERIMENT_TESTS = frozenset(
    {
        "conftest.py",  # the shared smoke run
        "helpers.py",
        "test_classify.py",  # its classifier comes from an experiment run
        "test_classify_hostile.py",
        "test_cli.py",
        "test_cross_season.py",
        "test_depth_training.py",  # also experiments.train_depth's overrides
        "test_experiment_config.py",
        "test_first_hour.py",
        "test_folder.py",
        "test_height_channel.py",
        "test_hha_diagnose.py",
        "test_models_dav2.py",  # a DAV2 run's classifier
        "test_pretrain.py",  # also experiments.pretrain_trunk's overrides
        "test_readme.py",
        "test_run_output.py",
        "test_scripts.py",
        "test_tracker.py",  # its classifier comes from an experiment run
        "test_unseen_diagnose.py",
    }
)


def test_library_tests_import_nothing_from_the_experiments():
    """The library's own test modules stand on the library: none imports ``experiments`` (at any level)."""
    tests = Path(__file__).resolve().parent
    offenders = {}
    for path in sorted(tests.glob("*.py")):
        if path.name in EXPERIMENT_TESTS or path.name == "test_layering.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            bad = [n for n in names if n == "experiments" or n.startswith("experiments.")]
            if bad:
                offenders.setdefault(path.name, []).extend(bad)
    assert not offenders, f"library test modules importing the experiments: {offenders}"
    assert len(list(tests.glob("test_*.py"))) - len(EXPERIMENT_TESTS) >= 25  # the library's modules are most
