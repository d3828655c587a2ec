"""The public surface: what ``dir(placejax)`` lists, lazy subpackages, every public name documented (with shapes
and units where it takes arrays), nothing underscored in ``__all__``; the in-memory session; the import graph."""

from __future__ import annotations

import ast
import inspect
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import placejax

PACKAGE = Path(placejax.__file__).parent
SUBPACKAGES = ("classify", "data", "depth", "hha", "io", "models", "pretrain", "training", "weights")


def _public_modules() -> dict[str, types.ModuleType]:
    """Every module reachable from ``placejax.__all__`` through the ``__all__`` of the modules it names."""
    seen: dict[str, types.ModuleType] = {}

    def walk(module: types.ModuleType) -> None:
        if module.__name__ in seen:
            return
        seen[module.__name__] = module
        for name in getattr(module, "__all__", ()):
            value = getattr(module, name)
            if isinstance(value, types.ModuleType) and value.__name__.startswith("placejax"):
                walk(value)

    walk(placejax)
    return seen


def _public_objects() -> list[tuple[str, object]]:
    out = []
    for modname, module in _public_modules().items():
        for name in getattr(module, "__all__", ()):
            value = getattr(module, name)
            if not isinstance(value, types.ModuleType):
                out.append((f"{modname}.{name}", value))
    return out


@pytest.mark.slow
def test_dir_lists_the_surface_and_subpackages_load_lazily():
    listed = set(dir(placejax))
    assert {"PlaceClassifier", "Prediction", "__version__", *SUBPACKAGES} <= listed
    assert set(placejax.__all__) <= listed
    # A fresh interpreter: `import placejax` imports no JAX, and `placejax.hha` works without importing it by hand.
    code = (
        "import sys, placejax; assert 'jax' not in sys.modules, 'import placejax pulled in JAX'; "
        "assert callable(placejax.hha.encode); assert placejax.PlaceClassifier.__name__ == 'PlaceClassifier'; "
        "assert placejax.data.simcampus.load_session; print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok", out.stderr
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        placejax.nope  # noqa: B018


def test_every_module_in_the_surface_has_a_complete_all():
    modules = _public_modules()
    assert {f"placejax.{m}" for m in SUBPACKAGES} <= set(modules)
    assert {"placejax.data.simcampus", "placejax.data.nclt"} <= set(modules)
    for modname, module in modules.items():
        assert hasattr(module, "__all__"), f"{modname} has no __all__"
        for name in module.__all__:
            assert not name.startswith("_"), f"{modname}.__all__ names the private {name!r}"
            assert hasattr(module, name), f"{modname}.__all__ names {name!r}, which it does not have"
        # Every public function or class defined in a package's private modules is exported somewhere.
    exported = {id(v) for _, v in _public_objects()}
    for modname, module in modules.items():
        for name, value in vars(module).items():
            if name.startswith("_") or not (inspect.isfunction(value) or inspect.isclass(value)):
                continue
            if getattr(value, "__module__", "").startswith(modname + "._"):
                assert id(value) in exported, f"{modname}.{name} is public but in no __all__"


def _documented_members() -> list[tuple[str, str]]:
    """``(full name, docstring)`` of every public name as the API reference reads it (pdoc's own model, which also
    finds the docstrings of constants: a string literal after the assignment, in the module that assigns it)."""
    import pdoc.doc

    def docstring(modname: str, name: str, value: object) -> str:
        member = pdoc.doc.Module(sys.modules[modname]).get(name)
        if member is not None and member.docstring.strip():
            return member.docstring
        # A constant re-exported by its package (or a public module of it): its docstring is where it is assigned,
        # in a private module of that package.
        packages = (modname + ".", modname.rpartition(".")[0] + ".")
        for other, module in list(sys.modules.items()):
            if other.startswith(packages) and module is not None and vars(module).get(name) is value:
                found = pdoc.doc.Module(module).get(name)
                if found is not None and found.docstring.strip():
                    return found.docstring
        return ""

    out = []
    for modname, module in _public_modules().items():
        out.append((modname, module.__doc__ or ""))
        for name in getattr(module, "__all__", ()):
            value = getattr(module, name)
            if not isinstance(value, types.ModuleType):
                out.append((f"{modname}.{name}", docstring(modname, name, value)))
    return out


def test_every_public_name_has_a_docstring():
    missing = [name for name, docstring in _documented_members() if not docstring.strip()]
    assert not missing, f"public names without a docstring: {missing}"


# A shape such as ``(N, H, W, 3)``, ``(3, 3)``, ``(B, ...)``, or the word "shape" / "scalar".
_SHAPE = re.compile(r"\(\s*[A-Za-z0-9_.…]+\s*,[^()]*\)|\([A-Z]\)|\bshape\b|\bscalar\b", re.I)
# Parameters taken to be arrays: annotated as one (not a mapping or callable of them), or unannotated and named so.
_ARRAY_ANNOTATION = re.compile(r"^(np\.ndarray|numpy\.ndarray|jax\.Array|Array|jnp\.ndarray|ArrayLike)\b")
_ARRAY_NAMES = re.compile(r"^(images?|rgb\w*|depths?|depth_m|inv\w*|x|k|intrinsics|logits|poses|hha\w*)$")


def _takes_arrays(fn) -> bool:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return False
    for p in sig.parameters.values():
        if p.name in ("key", "rng"):  # PRNG keys
            continue
        if p.annotation is inspect.Parameter.empty:
            if _ARRAY_NAMES.match(p.name):
                return True
        elif any(_ARRAY_ANNOTATION.match(part.strip()) for part in str(p.annotation).split("|")):
            return True
    return False


def test_public_functions_taking_arrays_give_shapes():
    """A heuristic: a public function or class whose signature takes arrays (annotated as arrays, or named like
    images, depth, intrinsics, logits) says which shapes in its docstring (or its class's)."""
    lacking = []
    for name, value in _public_objects():
        if inspect.isclass(value):
            fn, doc = value.__init__, (value.__doc__ or "") + (value.__init__.__doc__ or "")
        elif callable(value) and not isinstance(value, np.ndarray):
            fn, doc = value, value.__doc__ or ""
        else:
            continue
        if _takes_arrays(fn) and not _SHAPE.search(doc):
            lacking.append(name)
    assert not lacking, f"public callables taking arrays whose docstring gives no shape: {lacking}"


@pytest.mark.slow
def test_api_reference_builds_and_fails_on_a_broken_reference(tmp_path, monkeypatch):
    """``docs/build_api.py`` renders every public docstring without a warning, and a docstring naming a
    ``placejax.…`` object that does not exist fails it (pdoc alone would leave it as plain text)."""
    import importlib.util
    import warnings

    spec = importlib.util.spec_from_file_location("build_api", PACKAGE.parent / "docs" / "build_api.py")
    build_api = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build_api)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_api.build(tmp_path / "ok")
    assert "PlaceClassifier" in (tmp_path / "ok" / "placejax.html").read_text()
    assert (tmp_path / "ok" / "placejax" / "depth.html").is_file()
    broken = placejax.hha.encode.__doc__ + "\n\nSee `placejax.hha.no_such_function`.\n"
    monkeypatch.setattr(placejax.hha.encode, "__doc__", broken)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(build_api.UnresolvedReferenceWarning, match=r"placejax\.hha\.no_such_function"):
            build_api.build(tmp_path / "broken")


# ------------------------------------------------------------------------------------------- ArraySession


def test_array_session_satisfies_the_protocol_caches_and_names_bad_input(tmp_path):
    from placejax.data import ArraySession, Session, cache_session, session_identity, truncated

    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (5, 6, 4, 3), dtype=np.uint8)
    poses = rng.normal(size=(5, 3))
    k = np.array([[5.0, 0, 2.0], [0, 5.0, 3.0], [0, 0, 1]])
    s = ArraySession(images, poses, k, name="mine")
    assert isinstance(s, Session)
    assert len(s) == 5
    assert s.image_shape == (6, 4)
    np.testing.assert_array_equal(s.utimes, np.arange(5))
    cached = cache_session(s, tmp_path, progress=False)
    for i in range(len(s)):
        np.testing.assert_array_equal(cached.image(i), images[i])
    np.testing.assert_array_equal(cached.poses, poses)
    # The cache identity follows the content: other images, another identity; a cut session names the cut.
    other = ArraySession(images[::-1].copy(), poses, k, name="mine")
    assert session_identity(other) != session_identity(s)
    # ... wherever they differ: frame 1 of 5 is none of the first, middle and last frames a default identity samples
    edited = images.copy()
    edited[1, 0, 0, 0] ^= 1
    assert session_identity(ArraySession(edited, poses, k, name="mine")) != session_identity(s)
    assert session_identity(ArraySession(images.copy(), poses, k, name="mine")) == session_identity(s)
    assert len(truncated(s, 2)) == 2
    assert session_identity(truncated(s, 2))["fingerprint"]["truncated"] == 2
    with pytest.raises(ValueError, match=r"images must be uint8 \(N, H, W, 3\)"):
        ArraySession(images.astype(np.float32), poses, k)
    with pytest.raises(ValueError, match=r"poses must have shape \(5, 3\)"):
        ArraySession(images, poses[:4], k)
    with pytest.raises(ValueError, match=r"intrinsics must have shape \(3, 3\)"):
        ArraySession(images, poses, k[:2])
    with pytest.raises(ValueError, match=r"utimes must be integer microseconds of shape \(5,\)"):
        ArraySession(images, poses, k, utimes=np.zeros(5))
    with pytest.raises(IndexError, match="frame 5"):
        s.image(5)


def test_data_session_does_not_import_the_cache():
    """``data/session.py`` ↔ ``data/cache.py`` imported each other; the session module now stands alone."""
    tree = ast.parse((PACKAGE / "data" / "session.py").read_text())
    imported = {
        node.module if isinstance(node, ast.ImportFrom) else alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import | ast.ImportFrom)
        for alias in node.names
    }
    assert not {m for m in imported if m and m.startswith("placejax")}, imported


def _placejax_imports(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every placejax import of a file, at any depth (function-level imports included)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
    return [(line, m) for line, m in out if m.startswith("placejax")]


def test_no_package_imports_another_packages_private_module():
    """A name one subpackage needs from another is public where it lives: no ``placejax.<other>._private``."""
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        own = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        for line, module in _placejax_imports(path):
            parts = module.split(".")
            if len(parts) > 2 and parts[1] != own and any(p.startswith("_") for p in parts[2:]):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {module}")
    assert not bad, bad


def test_classify_does_not_import_stages():
    """One direction between the two: ``placejax.stages`` writes a run with ``placejax.classify``'s run layout and
    unseen-place scores; ``placejax.classify`` reads a finished run without the stages."""
    bad = [
        f"{path.name}:{line}: {module}"
        for path in sorted((PACKAGE / "classify").glob("*.py"))
        for line, module in _placejax_imports(path)
        if module == "placejax.stages" or module.startswith("placejax.stages.")
    ]
    assert not bad, bad
