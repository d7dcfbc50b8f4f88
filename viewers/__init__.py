"""Rerun entity layout, blueprints and logging; the text report; the summary PNG."""

from .rerun_log import ViewerInputError, build_blueprint, log_comparisons, report_markdown
from .summary_png import figure_size_px, png_path_for, write_summary_png

__all__ = ["ViewerInputError", "build_blueprint", "figure_size_px", "log_comparisons", "png_path_for",
           "report_markdown", "write_summary_png"]
