"""The report's Stage I table: per method and K, pooled ratios against the truth (not a mean
over every row and column of generator_metrics.csv, which mixed the generator with its
uniform baseline and averaged run numbers)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.report.tables import generator_summary


def metrics(k_used: list[int], method: str, std_spacing: list[float]) -> pd.DataFrame:
    n = len(k_used)
    return pd.DataFrame(
        {
            "method": method,
            "k_used": k_used,
            "speed_err_vs_psi_mps": np.linspace(0.0, 0.2, n),
            "std_speed_mps": 0.5,
            "true_std_speed_mps": 0.25,
            "std_spacing_m": std_spacing,
            "true_std_spacing_m": 10.0,
            "feasible": [True] * (n - 1) + [False],
        }
    )


def test_rows_per_method_and_k_with_pooled_ratios():
    df = pd.concat(
        [
            metrics([1, 1, 2, 2], "generator", [10.0, 20.0, 10.0, 10.0]),
            metrics([1, 1, 2, 2], "uniform", [30.0, 30.0, 40.0, 0.0]),
        ]
    )
    out = generator_summary(df).set_index(["method", "K"])
    assert list(out.index) == [("generator", 1), ("generator", 2), ("uniform", 1), ("uniform", 2)]
    # sqrt(mean(10^2, 20^2)) / 10 = sqrt(250) / 10
    assert out.loc[("generator", 1), "spacing_std_ratio"] == pytest.approx(np.sqrt(2.5))
    assert out.loc[("generator", 2), "spacing_std_ratio"] == pytest.approx(1.0)
    assert out.loc[("uniform", 2), "spacing_std_ratio"] == pytest.approx(np.sqrt(8.0))
    assert out["speed_std_ratio"].tolist() == pytest.approx([2.0] * 4)
    assert out["completions"].tolist() == [2, 2, 2, 2]
    # the last row of each method's frame is infeasible: K = 2 holds it
    assert out["infeasible_share"].tolist() == [0.0, 0.5, 0.0, 0.5]


def test_an_open_sections_many_estimated_counts_give_one_row_per_method():
    k = list(range(3, 33))  # an estimate per snapshot: 30 distinct counts
    out = generator_summary(metrics(k, "generator", [12.0] * len(k)))
    assert len(out) == 1
    assert out.loc[0, "K"] == pytest.approx(np.mean(k))
    assert out.loc[0, "spacing_std_ratio"] == pytest.approx(1.2)
