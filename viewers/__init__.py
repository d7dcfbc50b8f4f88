"""Rerun entity layout, blueprints and logging; the text report."""
