"""What a run reports: the scores of every method on every session pair (``scores``), the route filter's columns
(``route``), ``table.md`` (``table``) and the figures (``figures``)."""

from experiments.cross_season.report.figures import write_figures
from experiments.cross_season.report.route import route_columns, write_route_figures
from experiments.cross_season.report.scores import evaluate
from experiments.cross_season.report.table import table_markdown, write_table

__all__ = ["evaluate", "route_columns", "table_markdown", "write_figures", "write_route_figures", "write_table"]
