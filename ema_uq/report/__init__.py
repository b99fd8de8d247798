"""Reports: figures (matplotlib) and one self-contained HTML file per study."""
from __future__ import annotations

__all__ = ["build_report"]


def __getattr__(name: str):
    # lazy: the verbs that only write figure data (report.outputs) must not import matplotlib
    if name == "build_report":
        from .html import build_report
        return build_report
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
