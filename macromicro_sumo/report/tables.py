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


def generator_summary(metrics: pd.DataFrame) -> pd.DataFrame:
    """Stage I per method (the generator, its uniform baseline) and hidden count: held-out
    snapshots, |mean speed - psi's|, speed std and pooled spacing std over the truth's.

    Pooled (square root of the mean variance): on a closed loop every scene has the same
    mean spacing, so this is what the evaluation's spacing std reads; a mean of per-scene
    ratios would weigh a scene with two vehicles as much as one with twenty.
    """
    g = metrics.assign(method=metrics.get("method", "generator"))

    def pooled(x: pd.Series, y: pd.Series) -> float:
        return float(np.sqrt(np.nanmean(x**2) / np.nanmean(y**2)))

    # A row per K where the protocol sets a few (the ring's 1..4); an open section's
    # estimated K takes a value per snapshot, so there one row per method with the mean K.
    by_k = g["k_used"].nunique() <= 10
    rows = []
    for key, d in g.groupby(["method", "k_used"] if by_k else ["method"], sort=True):
        rows.append(
            {
                "method": key[0],
                "K": int(key[1]) if by_k else float(d["k_used"].mean()),
                "completions": len(d),
                "speed_err_vs_psi_mps": float(np.nanmean(d["speed_err_vs_psi_mps"])),
                "speed_std_ratio": pooled(d["std_speed_mps"], d["true_std_speed_mps"]),
                "spacing_std_ratio": pooled(d["std_spacing_m"], d["true_std_spacing_m"]),
                "infeasible_share": float(1.0 - d["feasible"].mean()),
            }
        )
    return pd.DataFrame(rows)
