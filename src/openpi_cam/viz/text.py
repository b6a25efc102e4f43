"""Numbers and tables as the reports print them: one place for how a figure is written."""

from __future__ import annotations

import html
import math
import numbers
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np


def escape(x: Any) -> str:
    return html.escape(str(x), quote=True)


def html_table(head: Sequence[str], rows: Sequence[Sequence[str]], raw: bool = False) -> str:
    """An HTML table; cells are escaped unless `raw` (cells that already hold markup)."""
    body = "".join("<tr>" + "".join(f"<td>{v if raw else escape(v)}</td>" for v in row) + "</tr>" for row in rows)
    return "<table><tr>" + "".join(f"<th>{escape(h)}</th>" for h in head) + f"</tr>{body}</table>"


def percent(x: float | None, decimals: int = 1) -> str:
    return "-" if x is None else f"{100 * x:.{decimals}f}%"


def number(x: Any, digits: int = 3) -> str:
    """`x` to `digits` significant digits; "-" for no value or a non-finite one."""
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}g}"


def finite_mean(values: Iterable[Any]) -> float | None:
    """The mean of the finite numbers among `values` (None and NaN skipped; a bool counts as 0 or 1, so a flag's mean
    is its rate); None when there is none."""
    v = [float(x) for x in values if isinstance(x, numbers.Real) and math.isfinite(x)]
    return float(np.mean(v)) if v else None
