"""What the macro alignment's tables say, in the report's words: the paper's ring figures
beside ours and the issue's targets (``alignment_verdicts``), and which method is closest to the
reference of a section's table (``closest_methods``: the recorded population or, for field
data, the stations; ``alignment_reference`` says which)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.evaluation.section import REFERENCE_STATIONS
from macromicro_sumo.report.tables import markdown_table

# The paper's ring results (Results and discussions): policy per K, and its ground truth.
PAPER_GT = {
    "mean_speed_mps": 12.06,
    "std_speed_mps": 0.37,
    "mean_spacing_m": 125.66,
    "std_spacing_m": 34.60,
}
PAPER_POLICY_SPEED = {1: 11.55, 2: 11.54, 3: 11.52, 4: 11.53}
PAPER_POLICY_SPEED_STD = "0.78-0.80"
PAPER_POLICY_SPACING_STD = "<= 34.79"


# The columns of macro_alignment.csv report.md shows: by hidden count K, and a section's.
RING_ALIGNMENT = (
    "K",
    "method",
    "mean_speed_mps",
    "std_speed_mps",
    "mean_spacing_m",
    "std_spacing_m",
    "collisions",
    "mean_speed_err_mps",
    "speed_err_ci_lo_mps",
    "speed_err_ci_hi_mps",
    "spacing_std_err_pct",
    "spacing_std_err_ci_lo_pct",
    "spacing_std_err_ci_hi_pct",
    "w1_speed_mps",
    "w1_accel_mps2",
    "w1_spacing_m",
)


SECTION_ALIGNMENT = (
    "hidden_count",
    "mean_k",
    "method",
    "mean_speed_mps",
    "std_speed_mps",
    "mean_spacing_m",
    "std_spacing_m",
    "vehicles_per_step",
    "collisions",
    "mean_speed_err_mps",
    "std_spacing_ratio",
    "w1_speed_mps",
    "w1_spacing_m",
    "station_speed_err_mps",
    "station_spacing_ratio",
)


def alignment_verdicts(align: pd.DataFrame) -> pd.DataFrame:
    """The issue's targets for ``policy`` per K, measured against the ground truth rows."""
    gt = align[align["method"] == "ground_truth"].set_index("K")
    pol = align[align["method"] == "policy"].set_index("K")
    rows = []
    for k in pol.index:
        g, p = gt.loc[k], pol.loc[k]
        rows.append(
            {
                "K": k,
                "speed error (m/s, <= 0.05)": abs(p["mean_speed_mps"] - g["mean_speed_mps"]),
                "speed std vs GT (%, within 25)": 100
                * (p["std_speed_mps"] / g["std_speed_mps"] - 1),
                "mean spacing - L/N (m)": p["mean_spacing_m"] - g["mean_spacing_m"],
                "spacing std vs GT (%, within 1.5)": 100
                * (p["std_spacing_m"] / g["std_spacing_m"] - 1),
                "its 95% interval (%)": _spacing_std_interval(p),
                "collisions (0)": str(int(p["collisions"])),
            }
        )
    return pd.DataFrame(rows)


def paper_policy(align: pd.DataFrame) -> list[str]:
    """The paper's policy per K and the issue's targets for ours."""
    paper = pd.DataFrame(
        [
            {
                "K": k,
                "method": "paper policy",
                "mean_speed_mps": v,
                "std_speed_mps": PAPER_POLICY_SPEED_STD,
                "mean_spacing_m": PAPER_GT["mean_spacing_m"],
                "std_spacing_m": PAPER_POLICY_SPACING_STD,
            }
            for k, v in PAPER_POLICY_SPEED.items()
        ]
    )
    return [
        f"The paper (its own ground truth: {PAPER_GT['mean_speed_mps']} m/s, std "
        f"{PAPER_GT['std_speed_mps']}):",
        "",
        markdown_table(paper, 2),
        "",
        "Targets for `policy`:",
        "",
        markdown_table(alignment_verdicts(align)),
        "",
    ]


def _spacing_std_interval(row: pd.Series) -> str:
    """'[lo, hi]' of a row's spacing-std error interval in % ('' in files from before it)."""
    lo = row.get("spacing_std_err_ci_lo_pct", np.nan)
    hi = row.get("spacing_std_err_ci_hi_pct", np.nan)
    return "" if pd.isna(lo) or pd.isna(hi) else f"[{lo:+.2f}, {hi:+.2f}]"


def is_field_alignment(align: pd.DataFrame | None) -> bool:
    """Whether macro_alignment.csv is against field stations (``evaluation.section``)."""
    return (
        align is not None
        and "reference" in align
        and bool((align["reference"] == REFERENCE_STATIONS).any())
    )


def alignment_reference(align: pd.DataFrame | None) -> str:
    """What the macro alignment's figures are against, for either data source."""
    stations = (
        "`station_speed_err_mps`: |mean over the scenes of the rollout's mean speed - the "
        "station interval's|; `station_spacing_ratio`: the rollouts' mean spacing over the "
        "stations' (1 / density per lane)."
    )
    if is_field_alignment(align):
        return (
            "Field data: the reference is the stations, not a recorded population. The "
            "`stations` row is each held-out scene's detector interval (their mean speed and "
            "spacing; stations measure no spread), and every method is compared with it: "
            f"{stations} Errors against the population (speed error, spread ratios, W1) are "
            "not computed: the recorded vehicles are the observed ones only. The generator "
            "completed the scenes with the hidden count estimated from the detectors "
            "(nobody counted the true one)."
        )
    return (
        "`hidden_count`: the generator completed the scenes with the estimated hidden count "
        "(what a user has) or the true one (what the estimate costs). Errors, ratios and W1 "
        "are against `ground_truth` (every recorded vehicle of the same scenes, simulated); "
        f"the `station_*` columns against each scene's detector interval: {stations}"
    )


# (column, words, distance from agreement): the figures the verdicts name a winner of.
VERDICTS = (
    ("mean_speed_err_mps", "closest mean speed", lambda x: x.abs()),
    ("std_spacing_ratio", "closest spacing spread", lambda x: (x - 1).abs()),
    ("w1_speed_mps", "closest speed distribution (W1)", lambda x: x.abs()),
    ("station_speed_err_mps", "closest mean speed to the stations", lambda x: x.abs()),
    ("station_spacing_ratio", "closest mean spacing to the stations", lambda x: (x - 1).abs()),
)
REFERENCE_ROWS = ("ground_truth", "stations")


def closest_methods(align: pd.DataFrame) -> list[str]:
    """Plain statements of which method is closest to the reference, per figure (those the
    table has and some method has a value of)."""
    out = []
    for label, g in align.groupby("hidden_count", sort=False):
        g = g[~g["method"].isin(REFERENCE_ROWS)]
        parts = []
        for col, words, distance in VERDICTS:
            if col not in g:
                continue
            d = distance(pd.to_numeric(g[col], errors="coerce"))
            if d.notna().any():  # idxmin of an all-NaN column raises (pandas 3)
                parts.append(f"{words}: **{g.loc[d.idxmin(), 'method']}**")
        if parts:
            out.append(f"- {label} hidden count: " + "; ".join(parts) + ".")
    return out + [""] if out else []
