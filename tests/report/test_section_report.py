"""The section report's macro-alignment text: what its figures are against for a simulated
and a field-data ground truth, and which method is closest per figure (never the
reference row, never a figure nobody has)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.evaluation.section import REFERENCE_RECORDED, REFERENCE_STATIONS
from macromicro_sumo.report.alignment import alignment_reference, closest_methods

NAN = np.nan


def simulated() -> pd.DataFrame:
    """macro_alignment.csv of a simulated truth: the ground truth row first; ``a`` is
    closest on speed, ``b`` on spacing spread, W1 and the stations."""
    rows = [
        ("ground_truth", 0.0, 1.00, 0.0, 0.50, 0.95),
        ("a", 0.2, 1.30, 1.5, 0.40, 0.80),
        ("b", 0.6, 0.95, 1.1, 0.10, 1.02),
    ]
    cols = [
        "method",
        "mean_speed_err_mps",
        "std_spacing_ratio",
        "w1_speed_mps",
        "station_speed_err_mps",
        "station_spacing_ratio",
    ]
    df = pd.DataFrame(rows, columns=cols)
    return df.assign(hidden_count="estimated", reference=REFERENCE_RECORDED)


def field() -> pd.DataFrame:
    """On field data: the ``stations`` row, the population's columns absent, and a method
    whose rollouts all ended at once (NaN)."""
    df = pd.DataFrame(
        {
            "method": ["stations", "a", "b", "c"],
            "station_speed_err_mps": [NAN, 1.1, 0.9, NAN],
            "station_spacing_ratio": [NAN, 0.95, 0.90, NAN],
        }
    )
    return df.assign(hidden_count="estimated", reference=REFERENCE_STATIONS)


def test_the_closest_method_per_figure_on_a_simulated_truth() -> None:
    lines = closest_methods(simulated())
    assert lines == [
        "- estimated hidden count: closest mean speed: **a**; closest spacing spread: **b**; "
        "closest speed distribution (W1): **b**; closest mean speed to the stations: **b**; "
        "closest mean spacing to the stations: **b**.",
        "",
    ]


def test_the_closest_method_on_field_data_and_all_nan_figures() -> None:
    # The population's figures are absent and the stations row is not a contender.
    assert closest_methods(field()) == [
        "- estimated hidden count: closest mean speed to the stations: **b**; "
        "closest mean spacing to the stations: **a**.",
        "",
    ]
    # A figure nobody has (every rollout ended at once) is left out, not a crash
    # (pandas 3's idxmin raises on an all-NaN column).
    empty = field().assign(station_spacing_ratio=NAN)
    assert closest_methods(empty)[0].endswith("closest mean speed to the stations: **b**.")
    assert closest_methods(empty.assign(station_speed_err_mps=NAN)) == []
    sim = simulated()
    sim.loc[sim["method"] != "ground_truth", "w1_speed_mps"] = NAN
    assert "W1" not in closest_methods(sim)[0] and "**a**" in closest_methods(sim)[0]


def test_the_text_names_the_reference_of_each_data_source() -> None:
    sim, fld = alignment_reference(simulated()), alignment_reference(field())
    assert "against `ground_truth`" in sim and "`station_*`" in sim
    assert "Field data" in fld and "`stations` row" in fld and "ground_truth" not in fld
    for text in (sim, fld):
        assert "`station_speed_err_mps`" in text and "`station_spacing_ratio`" in text
    # A folder without macro_alignment.csv (evaluation not run) reads as simulated.
    assert alignment_reference(None) == sim
