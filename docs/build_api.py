"""Builds the placejax API reference (HTML) from the docstrings with pdoc, failing on any warning.

    python -W error docs/build_api.py OUTPUT_FOLDER

Run as above (``-W error``, as ``.ci/run`` does), a pdoc warning fails the build, and so does a reference in a
docstring or annotation to a ``placejax.…`` name that does not resolve to a documented public object: pdoc itself
leaves such a reference as plain text, silently, so this script checks what pdoc's ``linkify`` left unlinked. The
HTML is not committed; ``OUTPUT_FOLDER/placejax.html`` is the entry page.
"""

from __future__ import annotations

import argparse
import re
import warnings
from pathlib import Path

try:
    import jinja2
    import pdoc
    import pdoc.doc
    import pdoc.render
    import pdoc.render_helpers
except ImportError as e:  # the plain install has no pdoc: say which extra brings it
    raise SystemExit(f'error: {e.name} is not installed: pip install -e ".[docs]" (pdoc and its jinja2)') from None

# pdoc's syntax highlighting splits "a.b" into "a</span><span class="o">.</span><span class="n">b".
_HIGHLIGHTED_DOT = re.compile(r'</span><span class="o">\.</span><span class="n">')
_LINK = re.compile(r"<a\b[^>]*>.*?</a>", re.S)
# Not inside a path or a quoted string (a format name such as "placejax.cross_season.classifiers" is no reference).
_PLACEJAX_NAME = re.compile(r"(?<![\w/.\-\"';])placejax(?:\.\w+)+")


class UnresolvedReferenceWarning(UserWarning):
    """A docstring names a ``placejax.…`` object that the API reference does not document."""


def _checked_linkify(linkify):
    @jinja2.pass_context
    def wrapper(context, code, namespace="", shorten=True):
        out = linkify(context, code, namespace, shorten)
        left = _LINK.sub("", _HIGHLIGHTED_DOT.sub(".", str(out)))
        for name in sorted(set(_PLACEJAX_NAME.findall(left))):
            module = context["module"].modulename
            warnings.warn(
                f"{module}{'.' + namespace if namespace else ''}: {name} does not resolve to a documented public "
                "placejax name",
                UnresolvedReferenceWarning,
                stacklevel=2,
            )
        return out

    return wrapper


def _load_lazy_names(module_name: str) -> None:
    # pdoc reads a module's __dict__; names that placejax imports on first use (PEP 562) are loaded first.
    import importlib
    import types

    module = importlib.import_module(module_name)
    for name in getattr(module, "__all__", ()):
        value = getattr(module, name)
        if isinstance(value, types.ModuleType) and value.__name__.startswith(module_name + "."):
            _load_lazy_names(value.__name__)


# pdoc cannot evaluate the string annotations of a NamedTuple's generated ``__new__`` in a module written with
# ``from __future__ import annotations`` (they are looked up in the generated function's namespace), nor flax's
# own ``ArrayTree`` alias of ``TrainState.opt_state``; the rendered signatures show the annotations as written.
_ANNOTATION_WARNINGS = (
    r"Error parsing type annotation .* for placejax\.data\.nclt\.\w+\.__init__\. Import of np failed",
    r"Error parsing type annotation .* for (flax\.training\.train_state|placejax\.training)\.TrainState\."
    r"(__init__|opt_state)\. Import of ArrayTree failed",
)


_PDOC_LINKIFY = pdoc.render_helpers.linkify


def build(output: Path) -> None:
    """Renders the HTML reference of ``placejax`` and its public submodules into ``output``."""
    for message in _ANNOTATION_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=UserWarning)
    _load_lazy_names("placejax")
    pdoc.doc.Module.from_name.cache_clear()  # a second build in one process reads the docstrings afresh
    # The templates hold the filter table they were set up with: the checked linkify goes there.
    pdoc.render.env.filters["linkify"] = _checked_linkify(_PDOC_LINKIFY)
    pdoc.render.configure(docformat="google", show_source=False, search=True)
    pdoc.pdoc("placejax", output_directory=output)


def main(argv: list[str] | None = None) -> None:
    """Command-line entry point: ``python -W error docs/build_api.py OUTPUT_FOLDER``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output", type=Path, help="folder for the HTML (not committed)")
    build(parser.parse_args(argv).output)


if __name__ == "__main__":
    main()
