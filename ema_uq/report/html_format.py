"""How the HTML report writes what it shows: numbers to the digits their uncertainty supports,
tables, figures embedded as PNG data, and a stage's result file read when it is there.

Every section of the report (:mod:`.html_estimation`, :mod:`.html_gap`, :mod:`.html`) writes
through these, so one number reads alike wherever it stands.
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from .. import io
from . import figures


def _table(header: list[str], rows: list[list[Any]], name_cols: int = 1) -> str:
    head = "".join(f'<th class="{"name" if i < name_cols else ""}">{html.escape(h)}</th>' for i, h in enumerate(header))
    body = []
    for row in rows:
        cells = "".join(f'<td class="{"name" if i < name_cols else ""}">{c}</td>' for i, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _fmt(x: float | None, digits: int = 5) -> str:
    if isinstance(x, str):
        return html.escape(x)
    if x is None or not np.isfinite(x):
        return '<span class="muted">–</span>'
    return f"{x:.{digits}g}"


def _decimals(sigma: float) -> int:
    """Decimal places that keep two significant digits of ``sigma`` (negative: round to tens...)."""
    return 1 - int(np.floor(np.log10(abs(sigma))))


def _uncertain(x: float, sigma: float) -> tuple[str, str, str]:
    """(x, sigma, power suffix) as text: two significant digits of sigma and x to the same
    place; very large or small magnitudes share one power of ten (suffix ``·10<sup>k</sup>``)."""
    big = max(abs(x), sigma)
    power = int(np.floor(np.log10(big))) if big > 0 else 0
    if -3 <= power < 5:
        d = _decimals(sigma)
        return _round(x, d), _round(sigma, d), ""
    scale = 10.0 ** power
    d = _decimals(sigma / scale)
    return _round(x / scale, d), _round(sigma / scale, d), f"·10<sup>{power}</sup>"


def _known(sigma: float | None) -> bool:
    return sigma is not None and bool(np.isfinite(sigma)) and sigma > 0


def _pm(x: float | None, sigma: float | None, fallback: int = 4) -> str:
    """``x ± sigma`` so that a number shows no digit its uncertainty does not support
    (:func:`_uncertain`). Without a finite positive sigma, x has ``fallback`` significant
    digits and the sigma shows as –."""
    if x is None or not np.isfinite(x):
        return _fmt(None)
    if not _known(sigma):
        return f"{_fmt(x, fallback)} ± {_fmt(None)}"
    xs, ss, power = _uncertain(x, sigma)
    return f"({xs} ± {ss}){power}" if power else f"{xs} ± {ss}"


def _at(x: float | None, sigma: float | None, fallback: int = 4) -> str:
    """``x`` alone to the place two significant digits of ``sigma`` give (interval ends, truths)."""
    if x is None or not np.isfinite(x):
        return _fmt(None)
    if not _known(sigma):
        return _fmt(x, fallback)
    xs, _, power = _uncertain(x, sigma)
    return xs + power


def _round(x: float, decimals: int) -> str:
    if decimals > 0:
        return f"{x:.{decimals}f}"
    return f"{round(x, decimals):.0f}"


#: called with a line after every figure drawn (the report stage's progress, installed by
#: :func:`ema_uq.report.html.build_report` for one report; None: silent)
PROGRESS = None


def _img(fig, alt: str) -> str:
    text = f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{figures.to_png_base64(fig)}">'
    if PROGRESS is not None:
        PROGRESS(f"drew {alt}")
    return text


def _png_file(path: Path, alt: str) -> str:
    import base64

    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}">'


def _read(results: Path, name: str) -> dict | None:
    return io.read_json(results / name) if (results / name).exists() else None
