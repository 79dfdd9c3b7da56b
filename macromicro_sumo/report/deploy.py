"""The deployment's figures and its section of report.md: every method driving the whole
population on the scenario's own demand, against the ground truth (docs/deploy.md).

Plots (PNG): the fundamental diagram (flow against density) per detector station, the
speed over time and space per lane (a heatmap) and the time-space diagram per lane, the
ground truth beside each method. ``deployment_markdown`` writes the section's text from
deploy_summary.csv alone: the table per method, in plain words where the detector-calibrated
IDM or the oracle is ahead of the policy and by how much, and what the targets' floors reach.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib as mpl
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from macromicro_sumo.deploy.compare import (
    ALL_LANES,
    DETECTOR_INTERVAL_COLUMNS,
    GEH_LIMIT,
    REFERENCE_FIELD,
    SPEED_TOLERANCE,
    read_outputs,
    truth_geometry,
)
from macromicro_sumo.report.deploy_manifest_lines import with_manifest_lines
from macromicro_sumo.report.deploy_words import acted_lines, oracle_check, reproduces_truth
from macromicro_sumo.report.plots import (
    METHOD_COLORS,
    REFERENCE_COLOR,
    SPEED_CMAP,
    TIME_SPACE_S,
    lane_figure,
    plot_time_space,
    save_figure,
    window,
)
from macromicro_sumo.report.tables import markdown_table

TRUTH = "ground_truth"
POLICY = "policy"
# The challengers the report measures the policy against, in words.
CHALLENGERS = {"idm_detectors": "the detector-calibrated IDM", "oracle": "the oracle"}
# The policy is also to beat these on speed RMSE (issue 17's criterion).
BASELINES = {"sumo_default": "SUMO's uncalibrated defaults", "idm_calibrated": "the fitted IDM"}
# The targets' floors on a truth (docs/deploy-log.md, "What a near-exact model reaches").
FLOORS = {
    "oracle_redrawn": "the true model with SUMO's random draws redrawn",
    "oracle_population": "the true model with its draws and each driver's parameters redrawn",
}
TARGET_SHARE = 0.85  # GEH < 5 and speed within 5% in at least 85% of station-intervals
MAX_STATIONS = 16  # fundamental diagrams drawn (the first ones along the road)
TIME_BIN_S = 10.0
SPACE_BINS = 60

# (column, header, how to print, higher is better)
SUMMARY_TABLE = (
    ("share_geh_below_5", f"GEH < {GEH_LIMIT:g} (%)", "pct", True),
    ("share_speed_within_5pct", f"speed within {SPEED_TOLERANCE:.0%} (%)", "pct", True),
    ("speed_rmse_mps", "speed RMSE (m/s)", "3f", False),
    ("density_rmse_vpkm", "density RMSE (veh/km)", "2f", False),
    ("w1_speed_mps", "W1 speed (m/s)", "3f", False),
    ("w1_accel_mps2", "W1 accel (m/s²)", "3f", False),
    ("w1_headway_s", "W1 headway (s)", "3f", False),
    ("w1_ttc_s", "W1 TTC (s)", "3f", False),
    ("collisions", "collisions", "int", False),
    ("teleports", "teleports", "int", False),
    ("emergency_brakings", "emergency brakings", "int", False),
    ("vehicle_steps_driven", "vehicle-steps driven", "int", None),
    ("safety_acted_share", "safety lowered (% of driven)", "pct", None),
    ("floor_acted_share", "floor raised (% of driven)", "pct", None),
)


def method_color(i: int) -> str:
    return METHOD_COLORS[i % len(METHOD_COLORS)]


# --------------------------------------------------------------------------- plots


def plot_fundamental_diagrams(comparison: pd.DataFrame, path: Path | str) -> Path:
    """Flow against density per station (every run and interval a point): the ground truth
    as black rings, each method in its colour. Stations without a flow (lane-area detectors) are
    left out; at most ``MAX_STATIONS`` stations, in the order of the road."""
    d = comparison[(comparison["lane"] == ALL_LANES) & comparison["flow_truth_vph"].notna()]
    if d.empty:
        raise ValueError("deploy comparison: no station with a flow to plot")
    order = d.groupby("station")["arc_m"].first().fillna(0.0).sort_values(kind="stable")
    stations = list(order.index[:MAX_STATIONS])
    methods = list(dict.fromkeys(d["method"]))
    cols = min(4, len(stations))
    rows = -(-len(stations) // cols)
    fig = Figure(figsize=(4.2 * cols, 3.6 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, station in zip(axes, stations, strict=False):
        s = d[d["station"] == station]
        truth = s.drop_duplicates(["run", "begin_s"])
        ax.scatter(
            truth["density_truth_vpkm"],
            truth["flow_truth_vph"],
            s=40,
            facecolors="none",
            edgecolors=REFERENCE_COLOR,
            label=TRUTH,
            zorder=2,
        )
        for i, m in enumerate(methods):
            g = s[s["method"] == m]
            ax.scatter(
                g["density_method_vpkm"],
                g["flow_method_vph"],
                s=12,
                color=method_color(i),
                alpha=0.7,
                label=m,
                zorder=3,
            )
        # From the origin: a fundamental diagram is read against (0, 0).
        k = s[["density_truth_vpkm", "density_method_vpkm"]].to_numpy(float)
        q = s[["flow_truth_vph", "flow_method_vph"]].to_numpy(float)
        ax.set_xlim(0.0, 1.08 * max(float(np.nanmax(k, initial=0.0)), 1.0))
        ax.set_ylim(0.0, 1.08 * max(float(np.nanmax(q, initial=0.0)), 1.0))
        ax.set_title(f"station {station}")
        ax.set_xlabel("density (veh/km, all lanes)")
        ax.set_ylabel("flow (veh/h, all lanes)")
        ax.grid(alpha=0.3)
    for ax in axes[len(stations) :]:
        ax.set_visible(False)
    axes[0].legend(fontsize="small")
    fig.suptitle("Fundamental diagram per station: ground truth and each deployed method")
    return save_figure(fig, path)


def plot_speed_heatmaps(
    lanes: Mapping[str, pd.DataFrame],
    path: Path | str,
    run: int,
    time_bin_s: float = TIME_BIN_S,
    space_bins: int = SPACE_BINS,
) -> Path:
    """Mean speed per cell of time and position, one row per lane (0 = rightmost) and one
    column per source (the ground truth first), for one run. ``lanes`` maps a source's name
    to its trajectories in ``lane_trajectories``' schema. Empty cells are white."""
    d = window(lanes, run)
    t0 = min(float(df["time_s"].min()) for df in d.values())
    t1 = max(float(df["time_s"].max()) for df in d.values())
    x1 = max(float(df["arc_m"].max()) for df in d.values())
    t_edges = np.arange(t0, t1 + time_bin_s, time_bin_s)
    x_edges = np.linspace(0.0, x1 + 1e-6, space_bins + 1)
    cmap = mpl.colormaps[SPEED_CMAP].with_extremes(bad="white")

    def draw(ax: Axes, g: pd.DataFrame, norm: Normalize) -> None:
        t, x, v = (g[c].to_numpy(float) for c in ("time_s", "arc_m", "speed_mps"))
        n, _, _ = np.histogram2d(t, x, bins=(t_edges, x_edges))
        s, _, _ = np.histogram2d(t, x, bins=(t_edges, x_edges), weights=v)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(n > 0, s / n, np.nan)
        ax.pcolormesh(t_edges, x_edges, np.ma.masked_invalid(mean).T, cmap=cmap, norm=norm)

    title = f"Speed over time and space per lane, run {run}"
    return lane_figure(d, path, title, cmap, draw)


def make_deploy_plots(
    truth_dir: Path | str,
    method_dirs: Mapping[str, Path | str],
    comparison: pd.DataFrame,
    plots_dir: Path | str,
    run: int | None = None,
) -> list[Path]:
    """The three figures into ``plots_dir`` (deploy_fundamental_diagram.png,
    deploy_speed_heatmap.png, deploy_time_space.png), for ``run`` (default: the first run
    compared); the trajectory figures only where the folders hold trajectories."""
    plots = Path(plots_dir)
    plots.mkdir(parents=True, exist_ok=True)
    made = [plot_fundamental_diagrams(comparison, plots / "deploy_fundamental_diagram.png")]
    geometry = truth_geometry(truth_dir)
    sources = {TRUTH: truth_dir, **method_dirs}
    lanes = {
        name: read_outputs(folder, geometry, leaders=False).lanes
        for name, folder in sources.items()
    }
    run = int(comparison["run"].min()) if run is None else run
    if any(len(df) and (df["run"] == run).any() for df in lanes.values()):
        made.append(plot_speed_heatmaps(lanes, plots / "deploy_speed_heatmap.png", run))
        ts = plots / "deploy_time_space.png"
        made.append(plot_time_space(lanes, ts, run, seconds=TIME_SPACE_S))
    return made


# --------------------------------------------------------------------------- report text


def cell(value: float, how: str) -> str:
    if not np.isfinite(value):
        return "n/a"
    if how == "pct":
        return f"{100 * value:.1f}"
    if how == "int":
        return f"{value:.0f}"
    return f"{value:.{how[0]}f}"


def intervals_s(summary: pd.DataFrame) -> tuple[float, float]:
    """(comparison interval, detectors' interval) [s] of a summary; NaN for a summary
    written before ``deploy.compare_interval_s`` (its figures are at the detectors')."""
    got = [
        float(summary[c].max()) if c in summary else np.nan
        for c in ("compare_interval_s", "detector_interval_s")
    ]
    return got[0], got[1]


def pooled(summary: pd.DataFrame) -> bool:
    """Whether the summary's figures are at a longer interval than the detectors'."""
    compare, detector = intervals_s(summary)
    return bool(np.isfinite(compare) and np.isfinite(detector) and compare > detector + 1e-9)


def pooled_coverage(summary: pd.DataFrame) -> float:
    """The share of the detectors' station-intervals the pooled comparison's whole blocks
    hold (1: they tile every run; Bremen's 720 s runs at 300 s: 600 / 720); NaN: unknown."""
    compare, detector = intervals_s(summary)
    col = "station_intervals_detector_interval"
    if col not in summary or not (np.isfinite(compare) and np.isfinite(detector)):
        return float("nan")
    held = float(summary["station_intervals"].max()) * round(compare / detector)
    total = float(summary[col].max())
    return held / total if total > 0 else float("nan")


def summary_markdown(summary: pd.DataFrame) -> str:
    """deploy_summary.csv as a markdown table, shares in percent; pooled to a longer
    interval, the shares at the detectors' own interval follow the pooled ones."""
    extra = []
    if pooled(summary):
        at = f" at {intervals_s(summary)[1]:g} s"
        extra = [
            (DETECTOR_INTERVAL_COLUMNS[col], head.replace(" (%)", f"{at} (%)"), how)
            for col, head, how, _ in SUMMARY_TABLE[:2]
        ]
    rows = []
    for _, r in summary.iterrows():
        row = {"method": str(r["method"]), "runs": f"{r['runs']:.0f}"}
        for i, (col, head, how, _) in enumerate(SUMMARY_TABLE):
            row[head] = cell(float(r.get(col, np.nan)), how)
            if i == 1:
                row |= {h: cell(float(r.get(c, np.nan)), w) for c, h, w in extra}
        rows.append(row)
    return markdown_table(pd.DataFrame(rows))


def gap_words(col: str, ahead: float, behind: float) -> str:
    """'by 12.5 percentage points (90.0% vs 77.5%)' / 'by 0.120 m/s (0.300 vs 0.420 m/s)'."""
    _, head, how, _ = next(x for x in SUMMARY_TABLE if x[0] == col)
    if how == "pct":
        return (
            f"by {100 * abs(ahead - behind):.1f} percentage points "
            f"({100 * ahead:.1f}% vs {100 * behind:.1f}%)"
        )
    unit = " " + head[head.find("(") + 1 : head.find(")")] if "(" in head else ""
    return f"by {cell(abs(ahead - behind), how)}{unit} ({cell(ahead, how)} vs {cell(behind, how)})"


def versus(summary: pd.DataFrame, challenger: str, words: str) -> list[str]:
    """Where ``challenger`` is ahead of the policy, and by how much; where it is not."""
    s = summary.set_index("method")
    p, c = s.loc[POLICY], s.loc[challenger]
    ahead, behind = [], []
    for col, head, _, higher in SUMMARY_TABLE:
        if higher is None or not (np.isfinite(p[col]) and np.isfinite(c[col])):
            continue
        if c[col] == p[col]:
            continue
        better = c[col] > p[col] if higher else c[col] < p[col]
        name = head.split(" (")[0]
        if better:
            ahead.append(f"{name} {gap_words(col, c[col], p[col])}")
        else:
            behind.append(name)
    who = f"- {words[0].upper()}{words[1:]} (`{challenger}`)"
    if not ahead and not behind:
        return [f"{who} is level with the policy on every figure."]
    if ahead:
        lines = [f"{who} is ahead of the policy on: " + "; ".join(ahead) + "."]
    else:
        lines = [f"{who} is ahead of the policy on nothing."]
    if behind:
        lines.append(f"  The policy is ahead of it on: {', '.join(behind)}.")
    return lines


def policy_targets(summary: pd.DataFrame) -> list[str]:
    """The policy against issue 17's targets: shares of 85% and speed RMSE below the
    uncalibrated defaults and the IDM fitted to the observed vehicles."""
    s = summary.set_index("method")
    p = s.loc[POLICY]
    compare, detector = intervals_s(summary)
    of = f" of {compare:g} s" if np.isfinite(compare) else ""
    lines = []
    for col, what in (
        ("share_geh_below_5", f"flow GEH < {GEH_LIMIT:g}"),
        ("share_speed_within_5pct", f"mean speed within {SPEED_TOLERANCE:.0%}"),
    ):
        if np.isfinite(p[col]):
            verdict = "met" if p[col] >= TARGET_SHARE else "missed"
            at = float(p.get(DETECTOR_INTERVAL_COLUMNS[col], np.nan))
            also = (
                f"; at the detectors' {detector:g} s: {100 * at:.1f}%"
                if pooled(summary) and np.isfinite(at)
                else ""
            )
            lines.append(
                f"- The policy: {what} in {100 * p[col]:.1f}% of station-intervals{of} "
                f"(target at least {TARGET_SHARE:.0%}): {verdict}{also}." + floor_words(s, col)
            )
    for name, words in BASELINES.items():
        if name in s.index and np.isfinite(s.loc[name, "speed_rmse_mps"]):
            theirs, ours = s.loc[name, "speed_rmse_mps"], p["speed_rmse_mps"]
            verdict = "better" if ours < theirs else "not better"
            lines.append(
                f"- Speed RMSE: policy {ours:.3f} m/s, {words} (`{name}`) {theirs:.3f} m/s: "
                f"the policy is {verdict}."
            )
    for name, words in FLOORS.items():
        if name in s.index and np.isfinite(s.loc[name, "speed_rmse_mps"]):
            lines.append(
                f"- Speed RMSE of {words} (`{name}`): {s.loc[name, 'speed_rmse_mps']:.3f} m/s "
                f"(the policy's: {p['speed_rmse_mps']:.3f} m/s)."
            )
    return lines


def floor_words(s: pd.DataFrame, col: str) -> str:
    """What the floors (``FLOORS``) reach of a share on this truth; "" without them."""
    out = ""
    for name, words in FLOORS.items():
        if name in s.index and np.isfinite(floor := s.loc[name, col]):
            gone = f": the {TARGET_SHARE:.0%} target is out of its reach here at this interval"
            gone = gone if floor < TARGET_SHARE else ""
            out += f" {words[0].upper()}{words[1:]} (`{name}`) reaches {100 * floor:.1f}%{gone}."
    return out


def is_field(summary: pd.DataFrame) -> bool:
    """Whether the summary is against field data (``deploy.compare``'s ``reference``)."""
    return "reference" in summary and (summary["reference"] == REFERENCE_FIELD).any()


def safety_lines(summary: pd.DataFrame) -> list[str]:
    """Collisions and teleports the ground truth does not have, and how often the safety
    layer acted on each speed-commanding method's commands."""
    field = is_field(summary)
    if field:  # a ground truth read from files counts none: nothing to subtract
        lines = ["- Field data records no collisions or teleports: those below are the methods'."]
    else:
        truth = summary["truth_collisions"].max(), summary["truth_teleports"].max()
        lines = [
            f"- Ground truth over the same runs: {cell(truth[0], 'int')} collisions, "
            f"{cell(truth[1], 'int')} teleports."
        ]
    bad = summary[(summary["collisions"].fillna(0) > 0) | (summary["teleports"].fillna(0) > 0)]
    for _, r in bad.iterrows():
        lines.append(
            f"- `{r['method']}`: {cell(r['collisions'], 'int')} collisions and "
            f"{cell(r['teleports'], 'int')} teleports"
            + (" in SUMO." if field else " the ground truth does not have.")
        )
    return lines + acted_lines(summary)


def reference_words(summary: pd.DataFrame) -> str:
    """What every figure of the summary is against: a simulated ground truth (its held-out
    runs re-run) or field data (the stations and the observed vehicles), ending with the
    summary's ``reference`` as written."""
    measures = (
        f"GEH < {GEH_LIMIT:g}: share of station-intervals whose flow passes the GEH test; "
        f"speed within {SPEED_TOLERANCE:.0%}: share whose space-mean speed is within "
        f"{SPEED_TOLERANCE:.0%} of the reference's"
    )
    if is_field(summary):
        text = (
            "Field data: every method drives the whole driven population of a SUMO run "
            "built for each held-out recording, on a demand rebuilt from the files (the "
            "scenario's route files, else SUMO's routeSampler on the station counts), with "
            "loops where the field stations are. The flow, speed and density figures are "
            "against the field stations' measurements, station by station and interval by "
            "interval from the end of the warm-up on (definitions: docs/deploy.md). "
            f"{measures}. W1 speed and accel are against the observed vehicles' "
            "distributions (a sample of the population); headway and TTC are not compared "
            "(n/a: who drove between two observed vehicles is unknown)."
        )
    else:
        text = (
            "Every method drives the whole driven population over the scenario's own demand "
            "and duration, on the ground truth's held-out runs (same demand, same seeds). "
            "Its detectors are compared with the ground truth's station by station and "
            f"interval by interval (definitions: docs/deploy.md). {measures}; W1: "
            "Wasserstein-1 distance to the ground truth's distribution (every vehicle)."
        )
    text = " ".join(filter(None, (text, interval_words(summary))))
    refs = summary["reference"].dropna().unique() if "reference" in summary else []
    if len(refs):
        text += f" Reference (`reference`): {'; '.join(map(str, refs))}."
    return text


def interval_words(summary: pd.DataFrame) -> str:
    """At which interval the shares, and so the targets, are judged."""
    compare, detector = intervals_s(summary)
    hourly = f"GEH < {GEH_LIMIT:g} in 85% of the counts is a criterion for hourly flows"
    if pooled(summary):
        text = (
            f"Station-intervals are of {compare:g} s (`deploy.compare_interval_s`): the "
            f"detectors' {detector:g} s intervals pooled (counts summed, space-mean speeds); "
            f"the targets are judged at {compare:g} s ({hourly}), and the shares at "
            f"{detector:g} s are given beside them."
        )
        share = pooled_coverage(summary)
        if share < 1.0 - 1e-6:
            text += (
                f" Only whole blocks of {compare:g} s are compared: they hold {share:.0%} of "
                f"the detectors' intervals, the rest of each run after its last whole block "
                "is not compared (a comparison interval that divides the run compares it all)."
            )
        return text
    if np.isfinite(detector):
        return (
            f"Station-intervals are the detectors' own {detector:g} s "
            f"(`deploy.compare_interval_s = 0`), where the targets are judged ({hourly}: "
            "at shorter intervals the test is stricter)."
        )
    return ""


def deployment_markdown(summary: pd.DataFrame, plots: Sequence[str] = ()) -> str:
    """The "Deployment" section of report.md from deploy_summary.csv; ``plots`` are image
    paths relative to report.md."""
    lines = [
        "## Deployment",
        "",
        reference_words(summary),
        "",
        summary_markdown(summary),
        "",
    ]
    methods = set(summary["method"])
    if POLICY in methods:
        lines += policy_targets(summary)
        for name, words in CHALLENGERS.items():
            if name == "oracle" and name in methods and reproduces_truth(summary, name):
                lines += oracle_check(summary, POLICY, list(FLOORS))
            elif name in methods:
                lines += versus(summary, name, words)
        lines.append("")
    lines += [*safety_lines(summary), ""]
    lines += [f"![{Path(p).stem}]({p})" for p in plots]
    return "\n".join(lines).rstrip() + "\n"


def deployment_section(run_dir: Path | str) -> list[str]:
    """report.md's "Deployment" lines of a run folder: from ``deploy/deploy_summary.csv``,
    the floors chosen in ``deploy/deploy_manifest.json`` and the figures in ``deploy/plots/``
    (paths relative to report.md); none when the run has no deployment."""
    deploy_dir = Path(run_dir) / "deploy"
    path = deploy_dir / "deploy_summary.csv"
    if not path.is_file():
        return []
    plots = sorted((deploy_dir / "plots").glob("*.png"))
    text = deployment_markdown(pd.read_csv(path), [f"deploy/plots/{p.name}" for p in plots])
    return [*with_manifest_lines(text.splitlines(), deploy_dir), ""]
