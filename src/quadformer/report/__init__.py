"""Benchmark outputs: tables in the paper's layout, figures and an offline HTML report."""

from quadformer.report._report import paper_tables, write_report

__all__ = ["paper_tables", "write_report"]
