"""report.md and plots for a section run: what the ring's report shows, on the user's road.

Plots (PNG, in ``DIR/plots``): time-space diagrams per lane of a held-out ground-truth run,
detectors against trajectories over time (speed, density) and the hidden-count estimate,
speed and spacing histograms per method, and both stages' training curves.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import matplotlib as mpl
import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from macromicro_sumo.evaluation.methods import methods_markdown
from macromicro_sumo.evaluation.section import REFERENCE_STATIONS
from macromicro_sumo.files import atomic_path
from macromicro_sumo.report.deploy import deployment_section
from macromicro_sumo.report.plots import (
    SPEED_CMAP,
    plot_distributions,
    plot_generator_training,
    plot_policy_training,
    save_figure,
)
from macromicro_sumo.report.tables import markdown_table, read_if_present, table_section
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.section import load_section_truth


def plot_lane_time_space(
    traj: pd.DataFrame, section: Section, run: int, path: Path, seconds: float = 300.0
) -> Path:
    """One panel per lane: arc position against time, a line per vehicle, coloured by speed."""
    d = traj[traj["run"] == run]
    d = d[d["time_s"] <= d["time_s"].min() + seconds]
    lanes = sorted(d["lane_index"].unique())
    norm = Normalize(float(d["speed_mps"].min()), float(d["speed_mps"].max()) + 1e-6)
    cmap = mpl.colormaps[SPEED_CMAP]
    fig = Figure(figsize=(5.0 * len(lanes) + 1.0, 5.0), layout="constrained")
    axes = fig.subplots(1, len(lanes), squeeze=False, sharey=True)[0]
    for ax, lane in zip(axes, lanes, strict=True):
        g = d[d["lane_index"] == lane].sort_values(["vehicle_id", "time_s"])
        segs, speeds = [], []
        for _, veh in g.groupby("vehicle_id", sort=True):
            t, x, v = (veh[c].to_numpy() for c in ("time_s", "arc_m", "speed_mps"))
            keep = (np.diff(t) > 0) & (np.diff(t) < 0.51 * 4) & (np.diff(x) >= 0)
            pts = np.column_stack([t, x])
            segs.append(np.stack([pts[:-1], pts[1:]], axis=1)[keep])
            speeds.append(0.5 * (v[:-1] + v[1:])[keep])
        if segs and sum(len(s) for s in segs):
            lc = LineCollection(np.concatenate(segs), cmap=cmap, norm=norm, linewidths=1.0)
            lc.set_array(np.concatenate(speeds))
            ax.add_collection(lc)
        ax.set_xlim(d["time_s"].min(), d["time_s"].max())
        ax.set_ylim(0.0, section.length_m)
        ax.set_title(f"lane {lane} (0 = rightmost)")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        for off in section.offsets_m[1:]:
            ax.axhline(off, color="grey", lw=0.5, ls=":")
    axes[0].set_ylabel("position along the section (m)")
    fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=cmap), ax=list(axes), label="speed (m/s)")
    fig.suptitle(f"Ground truth, run {run}: time-space diagram per lane (dotted: edge borders)")
    return save_figure(fig, path)


def plot_detectors_vs_truth(macro: pd.DataFrame, k_est: pd.DataFrame, path: Path) -> Path:
    """Per interval: detector vs trajectory speed and density; K estimate vs truth."""
    fig = Figure(figsize=(14, 4.2), layout="constrained")
    ax_v, ax_k, ax_h = fig.subplots(1, 3)
    for (src, g), style in zip(macro.groupby("source"), ("-", "--"), strict=False):
        g = g.sort_values(["run", "begin_s"])
        x = np.arange(len(g))
        ax_v.plot(x, g["mean_speed_mps"], ls=style, marker=".", label=src)
        ax_k.plot(x, g["density_vpkm_lane"], ls=style, marker=".", label=src)
    ax_v.set_title("Space-mean speed per interval")
    ax_v.set_ylabel("speed (m/s)")
    ax_k.set_title("Density per lane per interval")
    ax_k.set_ylabel("density (veh/km/lane)")
    for ax in (ax_v, ax_k):
        ax.set_xlabel("interval (runs one after another)")
        ax.legend()
        ax.grid(alpha=0.3)
    ax_h.scatter(k_est["k_true"], k_est["k_est"], s=10, alpha=0.6)
    lo, hi = 0, max(1, int(max(k_est["k_true"].max(), k_est["k_est"].max())) + 1)
    ax_h.plot([lo, hi], [lo, hi], color="black", lw=1)
    ax_h.set_xlabel("hidden vehicles, truth")
    ax_h.set_ylabel("hidden vehicles, estimated from detectors")
    err = k_est["k_error"].abs().mean() if len(k_est) else np.nan
    ax_h.set_title(f"Hidden count per snapshot (mean |error| {err:.2f} veh)")
    ax_h.grid(alpha=0.3)
    return save_figure(fig, path)


def make_section_plots(out: Path) -> list[Path]:
    plots = out / "plots"
    plots.mkdir(exist_ok=True)
    made = []
    truth = load_section_truth(out / "ground_truth")
    ev = json.loads((out / "evaluation" / "evaluation_manifest.json").read_text())
    run = int(ev["held_out_runs"][0])
    made.append(
        plot_lane_time_space(truth.trajectories, truth.section, run, plots / "time_space.png")
    )
    made.append(plot_detectors_vs_truth(truth.macro, truth.k_estimate, plots / "detectors.png"))
    samples = pd.read_csv(out / "evaluation" / "eval_samples.csv", dtype={"hidden_count": str})
    est = samples[samples["hidden_count"] == "estimated"]
    made.append(plot_distributions(est, plots / "distributions.png"))
    if (out / "generator" / "generator_train_log.csv").is_file():
        # A log without the ring's columns is skipped: the report's table still shows it.
        with contextlib.suppress(ValueError):
            made.append(
                plot_generator_training(
                    out / "generator" / "generator_train_log.csv", plots / "generator_training.png"
                )
            )
    if (out / "policy" / "policy_train_log.csv").is_file():
        made.append(
            plot_policy_training(
                out / "policy" / "policy_train_log.csv", plots / "policy_training.png"
            )
        )
    return made


def write_section_report(sc, out: Path, manifest: dict[str, Any]) -> Path:
    """report.md: the section, the ground truth, the K estimate, the stages' tables, plots."""
    plots = make_section_plots(out)
    gt = json.loads((out / "ground_truth" / "manifest.json").read_text())
    ev = json.loads((out / "evaluation" / "evaluation_manifest.json").read_text())
    align = read_if_present(out / "evaluation" / "macro_alignment.csv")
    micro = read_if_present(out / "evaluation" / "micro_consistency.csv")
    kdf = read_if_present(out / "evaluation" / "k_estimate_summary.csv")
    gen = read_if_present(out / "generator" / "generator_metrics.csv")
    runs = read_if_present(out / "ground_truth" / "runs.csv")
    vt = read_if_present(out / "ground_truth" / "vtypes.csv")
    lines = [
        f"# {sc.name}: macro-micro calibration on a SUMO section",
        "",
        f"Scenario `{sc.source}`, seed {sc.seed}. Section: {len(sc.section.edges)} edges "
        f"({', '.join(sc.section.edges)}), {'closed loop' if sc.section.closed else 'open corridor'}, "
        f"{gt['section_length_m']:.0f} m, lanes per edge {gt['section_lanes']}.",
        "",
        f"Car-following models of the demand (recorded, not assumed): "
        f"{', '.join(gt['car_following_models'])}. Detectors: {gt['detectors']['count']} "
        f"({gt['detectors']['source']}). Collisions {gt['collisions']}, teleports {gt['teleports']}.",
        "",
        "## Ground truth",
        "",
    ]
    if runs is not None:
        lines += [markdown_table(runs), ""]
    if vt is not None:
        lines += [markdown_table(vt), ""]
    lines += [
        "## Hidden count estimated from detector density",
        "",
        "K = round(vehicles on the section by the detectors) - observed vehicles, against the "
        "count the simulation knows.",
        "",
    ]
    if kdf is not None:
        lines += [markdown_table(kdf, 3), ""]
    if gen is not None:
        lines += table_section("Stage I: generator (held-out snapshots)", _summary(gen))
    lines += [
        "## Macro alignment (held-out runs)",
        "",
        *methods_markdown("sumo", set(align["method"]) if align is not None else set()),
        alignment_reference(align),
        "",
    ]
    if align is not None:
        cols = [
            c
            for c in (
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
            if c in align
        ]
        lines += [markdown_table(align[cols], 3), ""]
        lines += closest_methods(align)
    lines += table_section("Micro consistency (held-out observed actions)", micro)
    lines += [
        f"IDM calibrated on the observed vehicles: {json.dumps(ev.get('idm_calibrated', {}))}",
        "",
        *deployment_section(out),
        "## Plots",
        "",
    ]
    lines += [f"![{p.stem}](plots/{p.name})" for p in plots]
    lines += ["", "## Timings (s)", "", json.dumps(manifest.get("timings_s", {}), indent=1), ""]
    path = out / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path


def _summary(gen: pd.DataFrame) -> pd.DataFrame:
    """Means of the generator's per-snapshot metrics."""
    num = gen.select_dtypes("number")
    return num.mean().to_frame("mean").T


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
