"""``python -m experiments.cross_season.record RUN [--out docs/cross_season] --command "..."``: the committed record
of a run whose numbers the README and docs quote.

Writes into ``--out`` the run's ``results.json`` trimmed (no private per-frame fields; every mean, per-pair row,
interval, ceiling, baseline, route and unseen-place figure, timing and the config kept) with a ``record`` entry
saying which run, command and commit produced it, its ``table.md``, and the figures the README shows. The README's
table and headline figures are tested against this record (``tests/test_readme.py``), so a number quoted there
can only change with the record that backs it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from placejax import cli, io

__all__ = ["FIGURES", "main", "trimmed", "write_record"]

FIGURES = ("accuracy.png", "depth_hha.png", "examples.png", "workspace_map.png", "route_SU_AU.png")
"""The run's figures the README and docs show."""


def trimmed(results: dict) -> dict:
    """``results`` without its private fields (names starting with ``_``: per-frame arrays), recursively."""
    if isinstance(results, dict):
        return {k: trimmed(v) for k, v in results.items() if not str(k).startswith("_")}
    if isinstance(results, list):
        return [trimmed(v) for v in results]
    return results


def write_record(
    run: str | Path, out: str | Path, *, command: str, commit: str | None = None, note: str = "", figures: bool = True
) -> Path:
    """Writes the record of the finished run in ``run`` into ``out`` (see the module docstring); returns the
    record's ``results.json``.

    Raises:
        FileNotFoundError: ``run`` holds no finished run (no ``results.json``) or lacks a figure of :data:`FIGURES`.
    """
    run, out = Path(run), Path(out)
    path = run / "results.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: {run} is not a finished experiments.cross_season run")
    results = json.loads(path.read_text())
    missing = [f for f in FIGURES if figures and not (run / "figures" / f).is_file()]
    if missing:
        raise FileNotFoundError(f"{run}/figures lacks {missing}: record a run made with figures=True")
    commit = commit or results.get("commit")
    record = {"record": {"run": run.name, "command": command, "commit": commit, "note": note}, **trimmed(results)}
    target = out / "results.json"
    io.write_json(target, record)
    io.write_text(out / "table.md", (run / "table.md").read_text())
    for f in FIGURES if figures else ():
        io.write_bytes(out / f, (run / "figures" / f).read_bytes())
    return target


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.cross_season.record", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("run", type=Path, help="the finished run's work directory")
    parser.add_argument("--out", type=Path, default=Path("docs/cross_season"), help="where the record goes")
    parser.add_argument("--command", required=True, help="the command that made the run, as typed")
    parser.add_argument("--commit", default=None, help="the commit it ran (default: the one results.json records)")
    parser.add_argument("--note", default="", help="conditions worth saying (machine, load)")
    parser.add_argument("--no-figures", action="store_true", help="the numbers only (a run of extra columns)")
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    target = write_record(
        args.run, args.out, command=args.command, commit=args.commit, note=args.note, figures=not args.no_figures
    )
    print(f"record -> {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
