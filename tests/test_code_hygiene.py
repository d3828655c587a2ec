"""The code states what is, not when or why it changed: no dates and no issue numbers in the comments and docstrings
of any Python source of the repository (the story lives in CHANGELOG.md and docs/research-log.md)."""

import ast
import io
import re
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Dates of this project's history (data has dates of its own: NCLT's sessions are named by days of 2012 and 2013).
DATED = re.compile(r"\b20(2[4-9]|[3-9]\d)-[01]\d-[0-3]\d\b|\b[Ii]ssue #?\d+|(?<![\w&])#\d{2,}\b")


def prose(source: str) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment and docstring of a module."""
    out = [
        (tok.start[0], tok.string)
        for tok in tokenize.generate_tokens(io.StringIO(source).readline)
        if tok.type == tokenize.COMMENT
    ]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            doc = ast.get_docstring(node, clean=False)
            if doc is not None:
                out.append((node.body[0].lineno, doc))
    return out


def test_no_dates_or_issue_numbers_in_comments_or_docstrings():
    found = []
    for folder in ("placejax", "experiments", "benchmarks", "tests"):
        for path in sorted((REPO / folder).rglob("*.py")):
            if path == Path(__file__).resolve() or "fixtures" in path.parts:
                continue
            for line, text in prose(path.read_text(encoding="utf-8")):
                for m in DATED.finditer(text):
                    found.append(f"{path.relative_to(REPO)}:{line}: {m.group(0)!r}")
    assert not found, "\n".join(found)


def test_the_reader_sees_comments_and_docstrings_only():
    # The history-like words are assembled here, so that this file holds none of them itself.
    day, data_day = "-".join(("2026", "12", "05")), "-".join(("2026", "01", "10"))
    ticket, ref = "issue " + "7", "#" + "123"
    source = f'"""Module, {day}."""\n\nx = "{data_day}"  # {ticket}\n\n\ndef f():\n    """see {ref}"""\n'
    texts = " ".join(t for _, t in prose(source))
    assert sorted(m.group(0) for m in DATED.finditer(texts)) == sorted([ref, day, ticket])
    assert not DATED.search("colour = '#ff0000'")
    assert not DATED.search("1e-12")
    assert not DATED.search("the NCLT session 2012-01-22")
