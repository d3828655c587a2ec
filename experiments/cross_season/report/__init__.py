"""What a run reports: ``table.md`` (``table``, with the route table of ``route``) and the figures (``figures``,
``route``); the scores themselves come from ``placejax.stages.evaluate`` and ``placejax.stages.route_columns``."""

from experiments.cross_season.report.figures import write_figures
from experiments.cross_season.report.route import write_route_figures
from experiments.cross_season.report.table import table_markdown, write_table

__all__ = ["table_markdown", "write_figures", "write_route_figures", "write_table"]
