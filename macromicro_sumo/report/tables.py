"""Markdown tables of the reports, and reading the CSVs they show."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd


def markdown_table(df: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub markdown table (no extra dependency)."""
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, row in df.iterrows():
        cells = []
        for c in cols:
            v = row[c]
            if isinstance(v, float | np.floating):
                cells.append("" if np.isnan(v) else f"{v:.{digits}f}")
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def read_if_present(path: Path) -> pd.DataFrame | None:
    """The CSV at ``path``, or None where a stage did not write it."""
    return pd.read_csv(path) if path.is_file() else None


def table_section(
    title: str, df: pd.DataFrame | None, digits: int = 3, intro: Sequence[str] = ()
) -> list[str]:
    """A report section's lines: ``## title``, the ``intro`` lines and ``df`` as a table;
    none where the stage wrote no such CSV (``df`` None)."""
    if df is None:
        return []
    return [f"## {title}", "", *intro, markdown_table(df, digits), ""]
