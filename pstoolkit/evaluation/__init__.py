"""Scoring normal maps, tables of scored results and the evaluation report.

Until the release after 0.2 the package also answers for the module ``pstoolkit.evaluation`` it
replaces, whose names now live in ``pstoolkit.evaluation.scoring``.
"""

from pstoolkit.evaluation.scoring import (
    CSV_COLUMNS,
    GROUND_TRUTH_METRICS,
    METRICS,
    MISSING,
    PERCENT_METRICS,
    RESULT_FILE,
    TITLES,
    Record,
    Score,
    averages,
    collect,
    csv_text,
    format_value,
    json_text,
    markdown,
    markdown_table,
    read_capture_results,
    read_result_folder,
    score,
)

__all__ = [
    "CSV_COLUMNS", "GROUND_TRUTH_METRICS", "METRICS", "MISSING", "PERCENT_METRICS", "RESULT_FILE", "TITLES", "Record",
    "Score", "averages", "collect", "csv_text", "format_value", "json_text", "markdown", "markdown_table",
    "read_capture_results", "read_result_folder", "score",
]
