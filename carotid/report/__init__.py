"""The HTML report of a case (issue #6)."""

from carotid.report.html import build_report

__all__ = ["build_report"]
