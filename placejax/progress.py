"""Progress that reads well both in a terminal and in a log file.

In a terminal (standard error is a TTY) a long loop shows one live tqdm bar that disappears when the loop ends, and
stage lines (:func:`say`) print above it. Redirected to a file or a pipe, the same loops write whole lines instead —
a timestamp, the label, ``done/total``, the rate and the time left — once a loop has run for a third of
:data:`LOG_INTERVAL_S` seconds, then at most every :data:`LOG_INTERVAL_S` seconds, and when it ends (a loop that
ends sooner writes nothing): no carriage returns, nothing to clean up before the log can be read or grepped.

``PLACEJAX_PROGRESS=lines`` forces the line form in a terminal too, ``PLACEJAX_PROGRESS=bars`` the bars in a file;
``PLACEJAX_PROGRESS_INTERVAL=S`` sets the seconds between lines (default 30).

Example:
    >>> import io
    >>> out = io.StringIO()
    >>> with bar(total=3, desc="demo", unit="step", file=out, delay=0) as b:
    ...     b.update(3)
    >>> lines = out.getvalue().splitlines()
    >>> len(lines), "\\r" in out.getvalue(), lines[-1].split("  ", 1)[1].startswith("demo: 100%")
    (2, False, True)
"""

from __future__ import annotations

import os
import sys
import time
from typing import IO, Any

from tqdm import tqdm

__all__ = ["LOG_INTERVAL_S", "bar", "interactive", "say", "stamp"]

LOG_INTERVAL_S = 30.0
"""Seconds between two progress lines of one loop in a log (``PLACEJAX_PROGRESS_INTERVAL`` overrides it)."""


def _stream(file: IO[str] | None) -> IO[str]:
    return sys.stderr if file is None else file


def interactive(file: IO[str] | None = None) -> bool:
    """Whether progress on ``file`` (default standard error) is drawn as live bars rather than written as lines."""
    mode = os.environ.get("PLACEJAX_PROGRESS", "").strip().lower()
    if mode in ("lines", "log"):
        return False
    if mode in ("bars", "tty"):
        return True
    isatty = getattr(_stream(file), "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def _interval() -> float:
    try:
        value = float(os.environ.get("PLACEJAX_PROGRESS_INTERVAL", LOG_INTERVAL_S))
    except ValueError:
        return LOG_INTERVAL_S
    return value if value > 0 else LOG_INTERVAL_S


def stamp() -> str:
    """The local wall-clock time as ``HH:MM:SS`` (the prefix of every progress and stage line)."""
    return time.strftime("%H:%M:%S")


# A line of a log: no bar drawn with characters, the numbers only.
_LINE_FORMAT = (
    "{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} {unit} [{elapsed} elapsed, {remaining} left, {rate_fmt}{postfix}]"
)


class _LineBar(tqdm):
    """A tqdm whose every display is one whole timestamped line: the first once the loop has run ``delay`` seconds,
    then at most one every ``line_interval`` seconds, and a last one when it ends (tqdm itself asks about once a
    second; the lines in between are skipped)."""

    def __init__(self, *args, line_interval: float = LOG_INTERVAL_S, **kwargs):
        self._line_interval = line_interval
        self._last_wall: float | None = None
        self._last_meter: str | None = None
        super().__init__(*args, **kwargs)

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        # The values show on the next timed line; a line per update would flood the log.
        super().set_postfix(ordered_dict, refresh=False, **kwargs)

    def set_description(self, desc=None, refresh=True):
        super().set_description(desc, refresh=False)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        # tqdm asks for msg="" to erase the bar when it closes without `leave`: that is the moment for the last line.
        now = time.monotonic()
        closing = msg == ""
        if not closing and self._last_wall is not None and now - self._last_wall < self._line_interval:
            return False
        meter = self.format_meter(**self.format_dict)
        if meter != self._last_meter:  # the closing line may repeat the last timed one
            self._last_meter, self._last_wall = meter, now
            self.fp.write(f"{stamp()}  {meter}\n")
            self.fp.flush()
        return False  # nothing for tqdm to erase


def bar(
    iterable: Any = None,
    *,
    total: int | None = None,
    desc: str,
    unit: str = "it",
    initial: int = 0,
    disable: bool = False,
    file: IO[str] | None = None,
    **kwargs: Any,
) -> tqdm:
    """A progress bar over ``total`` items: a live tqdm bar in a terminal, timestamped lines in a file.

    Args:
        iterable: items to wrap and yield, as ``tqdm(iterable)`` (its length is the total when it has one).
        total: number of items (``None``: unknown, or the iterable's length).
        desc: the label, e.g. ``"train WI-rgb"``.
        unit: what an item is (``"frame"``, ``"step"``).
        initial: items already done (a resumed cache or training).
        disable: show nothing (the ``progress=False`` switch of every stage).
        file: where to write (default standard error).
        **kwargs: other tqdm options.

    Returns:
        A ``tqdm`` (use it as tqdm: ``update``, ``set_postfix``, a context manager, an iterable wrapper).
    """
    fp = _stream(file)
    if total is None and iterable is not None and hasattr(iterable, "__len__"):
        total = len(iterable)
    common = {"total": total, "desc": desc, "unit": unit, "initial": initial, "disable": disable, "file": fp}
    if interactive(file):
        return tqdm(iterable, leave=False, **common, **kwargs)
    interval = kwargs.pop("mininterval", None)
    interval = _interval() if interval is None else interval
    # A loop shorter than a third of the interval writes nothing: the stage line that follows says it was done.
    kwargs.setdefault("delay", interval / 3)
    kwargs.setdefault("mininterval", min(1.0, interval))  # how often tqdm asks; _LineBar keeps one line an interval
    kwargs.setdefault("maxinterval", max(1.0, interval))
    return _LineBar(
        iterable, line_interval=interval, leave=False, bar_format=_LINE_FORMAT if total else None, **common, **kwargs
    )


def say(message: str, *, file: IO[str] | None = None) -> None:
    """One timestamped line of a long job's story (a stage that starts or ends), printed above a live bar."""
    fp = _stream(file)
    line = f"{stamp()}  {message}"
    if interactive(file):
        tqdm.write(line, file=fp)
    else:
        fp.write(line + "\n")
        fp.flush()
