"""``python -m experiments.cross_season [--preset NAME] [--workdir DIR] [key=value ...]``."""

from __future__ import annotations

import argparse
import sys
import textwrap

from experiments.cross_season import config as _config
from placejax import cli


@cli.command
def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring); returns the exit status (130 after Ctrl-C: rerun to resume)."""
    parser = argparse.ArgumentParser(
        prog="python -m experiments.cross_season",
        description=(
            "The paper's cross-season place classification experiment (Table I): RGB-Net, HHA-Net on pseudo depth, "
            "the fusion MLP and the ablations on all 12 ordered season pairs. Resumable: rerun the same command "
            "after an interruption. Writes results.json, table.md and figures/ into the work directory."
        ),
        epilog=_config.help_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--preset", default="default", choices=_config.PRESETS, help="configuration preset")
    parser.add_argument("--workdir", default=None, help="work directory (default: runs/cross_season-<preset>)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. train.epochs=3")
    parser.add_argument(
        "--traceback", action="store_true", help="on a failure, the full traceback (also PLACEJAX_TRACEBACK=1)"
    )
    args = parser.parse_args(argv)

    # Multi-host launches must initialise before anything touches a JAX backend.
    from placejax.training import initialize_distributed

    initialize_distributed()
    cfg = _config.get_config(args.preset)
    try:
        _config.apply_overrides(cfg, args.overrides)
        _config.validate(cfg)
    except ValueError as e:
        # One line a user can act on: every bad key with what it needs, and where the keys are listed.
        head, *problems = [line.strip() for line in str(e).splitlines() if line.strip()]
        message = f"{head} {'; '.join(problems)}" if problems else head
        raise SystemExit(f"{message} (python -m experiments.cross_season --help lists every key)") from None
    from pathlib import Path

    from experiments.cross_season.driver import duration, run
    from experiments.cross_season.report.table import table_text

    workdir = Path(args.workdir or f"runs/cross_season-{args.preset}")
    try:
        results = run(cfg, workdir)
    except KeyboardInterrupt:
        # Every finished stage is cached and every training checkpointed: nothing is lost.
        print(
            f"\ninterrupted: rerun the same command to resume where it stopped (work directory {workdir})",
            file=sys.stderr,
        )
        return 130
    print(table_text(results))
    t = results["timings_s"]
    peak = results.get("peak_rss_mib", {}).get("total")
    stages_line = ", ".join(f"{k} {duration(v)}" for k, v in t.items() if k != "total" and v >= 0.5)
    summary = f"stage times: {stages_line}" + (f"; peak memory {peak / 1024:.2f} GiB" if peak else "")
    print("\n" + "\n".join(textwrap.wrap(summary, 100, subsequent_indent="  ")))
    figures = " and figures/" if (workdir / "figures").is_dir() else ""
    print(f"done in {duration(t.get('total', 0.0))}: {workdir}/ holds table.md, results.json{figures}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
