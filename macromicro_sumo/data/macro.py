"""Psi from the detectors' passages: spacing estimates from consecutive passages at a loop,
and speed or spacing bounds widened from a sample's extremes (the loss terms on Psi:
``data.objective``; the section's macro statistics: ``truth.section_macro``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd


def extended_bounds(lo: Any, hi: Any, n: Any) -> tuple[Any, Any]:
    """[lo, hi], the extremes of n samples, widened by (hi - lo) / (n - 1) on each side
    (``generator.bounds_source = "extended"``, ring and sections): n draws' range covers on
    average (n - 1) / (n + 1) of the distribution, and range / (n - 1) each side is the
    classical correction of the ends. Crossed bounds stay as measured; n < 2 counts as 2."""
    widen = np.maximum(np.subtract(hi, lo), 0.0) / (np.maximum(n, 2.0) - 1.0)
    return lo - widen, hi + widen


def passage_spacings(passages: pd.DataFrame) -> pd.DataFrame:
    """Spacing estimates from consecutive passages at each instantaneous loop.

    Spacing = time headway x mean of the two passage speeds: the distance the leader
    covered between its passage and the follower's, for near-constant speeds.
    """
    out = []
    for _, g in passages.sort_values(["run", "detector_id", "time_s"]).groupby(
        ["run", "detector_id"]
    ):
        t, v = g["time_s"].to_numpy(), g["speed_mps"].to_numpy()
        if len(t) < 2:
            continue
        out.append(
            pd.DataFrame(
                {
                    "run": g["run"].to_numpy()[1:],
                    "detector_id": g["detector_id"].to_numpy()[1:],
                    "time_s": t[1:],
                    "spacing_m": np.diff(t) * 0.5 * (v[1:] + v[:-1]),
                }
            )
        )
    cols = ["run", "detector_id", "time_s", "spacing_m"]
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=cols)
