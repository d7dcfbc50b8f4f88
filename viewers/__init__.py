"""Rerun entity layout, blueprints and logging; the text report; the summary PNG."""

from .comparisons import ViewerInputError
from .layout import build_blueprint
from .report import report_markdown
from .rerun_log import log_comparisons
from .summary_png import figure_size_px, png_path_for, write_summary_png

__all__ = ["ViewerInputError", "build_blueprint", "figure_size_px", "log_comparisons", "png_path_for",
           "report_markdown", "write_summary_png"]
