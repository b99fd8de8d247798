"""Reports: figures (matplotlib) and one self-contained HTML file per study."""
from .html import build_report

__all__ = ["build_report"]
