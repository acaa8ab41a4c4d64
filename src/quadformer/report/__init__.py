"""Reports: the detection benchmark's tables in the paper's layout, figures and an offline
HTML report; the resilience benchmark's policy tables and trajectory figures."""

from quadformer.report.detection import write_report
from quadformer.report.detection_tables import dataset_table, paper_tables
from quadformer.report.resilience import overall_table, write_resilience_report

__all__ = ["dataset_table", "overall_table", "paper_tables", "write_report", "write_resilience_report"]
