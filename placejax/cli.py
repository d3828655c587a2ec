"""How placejax's command lines end when they fail: one line on stderr naming the cause, exit status 2.

Every ``main`` of a placejax command (``python -m placejax.classify``, ``python -m experiments.cross_season``, the
benchmarks, ...) is wrapped by :func:`command`:

* an exception ends in **one line** on stderr, ``error: <message>``, and exit status 2. An ``OSError`` from the
  operating system names its errno and path: ``error: ENOSPC: no space left on device while writing
  runs/x/config.json``;
* Ctrl-C ends with exit status 130 and, where the command can resume, how (``interrupted: rerun ...``);
* the traceback is printed too only when asked: ``--traceback`` anywhere before a ``--`` on the command line (taken
  out before the command parses its arguments), or ``PLACEJAX_TRACEBACK=1`` in the environment;
* a command's own exits are its own: argparse's usage errors (status 2, with the usage line) and other integer
  exit codes pass through; run as the process's command, a ``SystemExit("message")`` ends like any failure.

After a failure the process stays quiet: the exception's frames are released while the interpreter can still run
the finalisers of the work they held (orbax's abandoned write coroutines otherwise ran at shutdown and printed
``ImportError: sys.meta_path is None``), and, in a process about to exit, helper threads still failing report
nothing more.

Example::

    from placejax import cli

    @cli.command(interrupted="rerun the same command to resume")
    def main(argv: list[str] | None = None) -> int:
        ...

    if __name__ == "__main__":
        sys.exit(main())
"""

from __future__ import annotations

import contextlib
import errno
import functools
import gc
import logging
import os
import sys
import threading
import traceback
from collections.abc import Callable, Sequence

__all__ = [
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "TRACEBACK_ENV",
    "TRACEBACK_FLAG",
    "check_jax_platforms",
    "command",
    "describe",
]

EXIT_FAILURE = 2
"""Exit status of a command that failed."""
EXIT_INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT, as a shell reports it)."""
TRACEBACK_FLAG = "--traceback"
"""The option that makes a failing command print its traceback (taken out of argv by :func:`command`)."""
TRACEBACK_ENV = "PLACEJAX_TRACEBACK"
"""Set to ``1`` to make every failing command print its traceback."""
TRACEBACK_HELP = f"on failure, print the full traceback too (or set {TRACEBACK_ENV}=1)"
"""Help text of :data:`TRACEBACK_FLAG` for a command that lists it in its ``--help``."""

_MAX_CHARS = 2000
# The message alone says it for these and placejax's own; any other (a bug: TypeError, KeyError, ...) gets its name.
_PLAIN = (ValueError, RuntimeError, OSError)
_OWN_PACKAGES = ("placejax", "experiments", "benchmarks")
# Phrases after which the path reads on without a colon ("... while writing /x").
_LEADS_INTO_PATH = ("writing", "reading", "creating", "opening")

Main = Callable[[list[str]], int | None]


def describe(error: BaseException) -> str:
    """The one-line message of ``error`` (without the ``error:`` prefix).

    >>> describe(OSError(errno.ENOSPC, "No space left on device while writing", "/runs/x/config.json"))
    'ENOSPC: no space left on device while writing /runs/x/config.json'
    >>> describe(FileNotFoundError(errno.ENOENT, "No such file or directory", "/data/WI"))
    'ENOENT: no such file or directory: /data/WI'
    >>> describe(KeyError("rgb"))
    "KeyError: 'rgb'"
    """
    if isinstance(error, OSError) and error.errno in errno.errorcode:
        text = error.strerror or os.strerror(error.errno)
        text = text[:1].lower() + text[1:]
        paths = " -> ".join(os.fsdecode(p) for p in (error.filename, error.filename2) if p is not None)
        if paths:
            text += (" " if text.endswith(_LEADS_INTO_PATH) else ": ") + paths
        message = f"{errno.errorcode[error.errno]}: {text}"
    else:
        message = str(error)
        kind = type(error)
        if not message or not (isinstance(error, _PLAIN) or kind.__module__.split(".")[0] in _OWN_PACKAGES):
            message = f"{kind.__name__}: {message}" if message else kind.__name__
    message = " ".join(message.split())  # one line, whatever the message quotes
    return message if len(message) <= _MAX_CHARS else message[: _MAX_CHARS - 1] + "…"


def command(main: Main | None = None, *, interrupted: str | None = None) -> Callable:
    """Wraps a command's ``main(argv)`` (see the module docstring); use as ``@command`` or
    ``@command(interrupted="rerun the same command to resume")``.

    The wrapped ``main(argv=None)`` reads ``sys.argv[1:]`` when ``argv`` is None (as the process's command: ``python
    -m``, a console script) and returns the exit status instead of raising: ``main``'s own, :data:`EXIT_FAILURE`
    after an exception, :data:`EXIT_INTERRUPTED` after Ctrl-C.

    Args:
        main: ``main(argv: list[str]) -> int | None``.
        interrupted: what to tell the user after Ctrl-C (e.g. how to resume); None: only that it was interrupted.
    """

    def wrap(fn: Main) -> Callable[[Sequence[str] | None], int | None]:
        @functools.wraps(fn)
        def run(argv: Sequence[str] | None = None) -> int | None:
            entry = argv is None
            args = list(sys.argv[1:] if entry else argv)
            show = _take_flag(args) or os.environ.get(TRACEBACK_ENV, "") not in ("", "0")
            helpers = _HelperThreadTracebacks()
            if not show:
                logging.getLogger("absl").addFilter(helpers)
            try:
                if "-h" not in args and "--help" not in args:
                    check_jax_platforms()
                return fn(args)
            except KeyboardInterrupt:
                _flush()
                print(f"\ninterrupted: {interrupted}" if interrupted else "\ninterrupted", file=sys.stderr)
                return EXIT_INTERRUPTED
            except SystemExit as e:
                if not entry or e.code is None or isinstance(e.code, int):
                    raise
                _fail(RuntimeError(str(e.code)), show=False, entry=entry)
                return EXIT_FAILURE
            except Exception as e:
                _fail(e, show=show, entry=entry)
                return EXIT_FAILURE
            finally:
                logging.getLogger("absl").removeFilter(helpers)

        return run

    return wrap if main is None else wrap(main)


class _HelperThreadTracebacks(logging.Filter):
    """Drops what a helper thread logs with a traceback (orbax's writer threads log the exception that the command
    itself then raises, and reports in one line): without ``--traceback`` a failure is told once, in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.exc_info and threading.current_thread() is not threading.main_thread())


def check_jax_platforms() -> None:
    """With ``JAX_PLATFORMS`` naming another platform than the CPU (``cuda``, ``tpu``), checks that JAX finds it
    before any work, since JAX itself then fails with a bare ``AssertionError`` at its first array.

    Raises:
        RuntimeError: naming the variable, its value, and the two ways out.
    """
    wanted = os.environ.get("JAX_PLATFORMS", "").strip()
    if not wanted or wanted.lower() == "cpu":
        return
    import jax

    try:
        jax.devices()
    except Exception as e:  # JAX's own: AssertionError, or RuntimeError naming the plugin
        detail = f" ({type(e).__name__}: {e})" if str(e) else ""
        raise RuntimeError(
            f"JAX_PLATFORMS={wanted!r}: JAX found no such platform on this machine{detail}; for an NVIDIA GPU "
            "install placejax with the cuda12 extra (docs/gpu.md), or unset JAX_PLATFORMS to run on the CPU"
        ) from None


def _take_flag(args: list[str]) -> bool:
    """Removes every :data:`TRACEBACK_FLAG` before a ``--`` (what follows belongs to another command)."""
    end = args.index("--") if "--" in args else len(args)
    found = TRACEBACK_FLAG in args[:end]
    args[:end] = [a for a in args[:end] if a != TRACEBACK_FLAG]
    return found


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed or full stream: nothing more can be said on it
            stream.flush()


def _fail(error: Exception, *, show: bool, entry: bool) -> None:
    _flush()
    if show:
        traceback.print_exception(error)
    print(f"error: {describe(error)}", file=sys.stderr)
    _flush()
    _release(error)
    if entry:
        _quiet_until_exit()


def _release(error: BaseException) -> None:
    """Drops the locals of every frame of ``error``'s traceback (and its causes'), then collects, so that what they
    held — orbax's abandoned write coroutines, open files — is finalised now, not during interpreter shutdown."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        traceback.clear_frames(error.__traceback__)
        error = error.__cause__ or error.__context__
    gc.collect()


def _quiet_until_exit() -> None:
    """A command that failed is about to exit: what its helper threads still report (the same failure, from the
    writes they were doing) is not shown."""
    sys.unraisablehook = lambda unraisable: None
    threading.excepthook = lambda args: None
    logging.disable(logging.CRITICAL)
