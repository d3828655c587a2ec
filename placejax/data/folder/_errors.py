"""The one error type of session folders, and quoting that never echoes a huge string."""

from __future__ import annotations

from pathlib import Path

QUOTE_CHARS = 80
"""The most characters of a file's own text (a value, a file name) an error message quotes."""


class FolderFormatError(ValueError):
    """A malformed session folder; the message starts with ``path:line:`` or ``path:``."""


class MissingSessionError(FolderFormatError, FileNotFoundError):
    """A session folder (or the folder of sessions) that is not there; also a :class:`FileNotFoundError`."""


def _err(path: Path | str, line: int | None, msg: str, kind: type[FolderFormatError] = FolderFormatError):
    """``kind("path:line: msg")`` (``"path: msg"`` when no line is to blame)."""
    return kind(f"{path}:{line}: {msg}" if line is not None else f"{path}: {msg}")


def _quote(value: object, limit: int = QUOTE_CHARS) -> str:
    """``repr(value)`` of at most about ``limit`` characters, saying how long the whole was when it is cut.

    Example:
        >>> _quote("x" * 5000, 10)
        "'xxxxxxxxx'… (5000 characters)"
    """
    if isinstance(value, str) and len(value) > limit:
        return f"{value[: limit - 1]!r}… ({len(value)} characters)"
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 1]}… ({len(text)} characters)"
