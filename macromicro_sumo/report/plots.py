"""Evaluation figures as PNG files: leader-follower profiles, time-space diagrams (any
road: a row per lane, a column per source), detectors against trajectories,
speed/spacing distributions and training curves.

Every function takes DataFrames (or CSV paths) and writes one PNG atomically (a temporary
name in the same folder, then ``os.replace``). Figures are built with ``matplotlib.figure``
directly, not pyplot: no display, no global backend switch, no figures left open.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import matplotlib as mpl
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import Colormap, Normalize
from matplotlib.figure import Figure

from macromicro_sumo.files import atomic_path

DPI = 120
LEADER_COLOR = "tab:green"
IDM_COLOR = "tab:blue"
REFERENCE_COLOR = "black"
# Learned methods: the first is orange as in the paper's Fig. 3.
METHOD_COLORS = ("tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
SPEED_CMAP = "RdYlGn"  # red = slow, green = fast, as in traffic-state maps
TIME_SPACE_S = 300.0  # a run's time-space diagram: its first seconds (lines stay readable)


def save_figure(fig: Figure, path: Path | str) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path


def _frame(data: pd.DataFrame | Path | str) -> pd.DataFrame:
    return data if isinstance(data, pd.DataFrame) else pd.read_csv(data)


def _require(df: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what}: missing columns {', '.join(missing)}")
    if df.empty:
        raise ValueError(f"{what}: no rows to plot")


# --------------------------------------------------------------------------- leader-follower


def plot_leader_follower(
    traces: pd.DataFrame | Path | str, path: Path | str, idm_method: str = "IDM"
) -> Path:
    """Fig. 3 of the paper: per scenario, speed (left) and gap (right) against time.

    ``traces`` has the columns of ``leader_follower.csv``. The leader is green, the IDM
    follower blue, every trial of a learned method thin and their mean thick (orange for
    the first method).
    """
    df = _frame(traces)
    cols = ["scenario", "method", "trial", "time_s", "leader_speed_mps", "follower_speed_mps"]
    _require(df, [*cols, "gap_m"], "leader-follower traces")
    scenarios = list(dict.fromkeys(df["scenario"]))
    methods = [m for m in dict.fromkeys(df["method"]) if m != idm_method]
    fig = Figure(figsize=(12, 3.6 * len(scenarios)), layout="constrained")
    axes = fig.subplots(len(scenarios), 2, squeeze=False, sharex=True)
    for row, scenario in zip(axes, scenarios, strict=True):
        d = df[df["scenario"] == scenario]
        ax_v, ax_g = row
        # Every row carries the leader; a trial cut short by a collision must not cut it.
        lead = d.groupby("time_s")["leader_speed_mps"].first()
        ax_v.plot(
            lead.index,
            lead.to_numpy(),
            color=LEADER_COLOR,
            lw=2.5,
            label="leader (prescribed)",
        )
        for j, method in enumerate(methods):
            color = METHOD_COLORS[j % len(METHOD_COLORS)]
            m = d[d["method"] == method]
            n = m["trial"].nunique()
            for k, (_, tr) in enumerate(m.groupby("trial")):
                label = f"{method}: {n} trials" if k == 0 else None
                ax_v.plot(
                    tr["time_s"],
                    tr["follower_speed_mps"],
                    color=color,
                    lw=0.6,
                    alpha=0.35,
                    label=label,
                )
                ax_g.plot(tr["time_s"], tr["gap_m"], color=color, lw=0.6, alpha=0.35)
            mean = m.groupby("time_s")[["follower_speed_mps", "gap_m"]].mean()
            ax_v.plot(
                mean.index,
                mean["follower_speed_mps"],
                color=color,
                lw=2.5,
                label=f"{method}: mean of trials",
            )
            ax_g.plot(mean.index, mean["gap_m"], color=color, lw=2.5)
        idm = d[d["method"] == idm_method]
        if not idm.empty:
            ax_v.plot(
                idm["time_s"],
                idm["follower_speed_mps"],
                color=IDM_COLOR,
                lw=2.5,
                ls="--",
                label="IDM follower (ground truth)",
            )
            ax_g.plot(idm["time_s"], idm["gap_m"], color=IDM_COLOR, lw=2.5, ls="--")
        v0, v1 = lead.iloc[[0, -1]]
        verb = {"accelerate": "accelerates", "decelerate": "decelerates"}.get(scenario, scenario)
        ax_v.set_title(f"{scenario}: leader {verb} {v0:g} → {v1:g} m/s — speed")
        ax_g.set_title(f"{scenario}: follower's gap to the leader")
        ax_v.set_ylabel("speed (m/s)")
        ax_g.set_ylabel("gap, bumper to bumper (m)")
        ax_v.legend(loc="best", fontsize="small")
        for ax in row:
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    return save_figure(fig, path)


# --------------------------------------------------------------------------- time-space


def window(
    sources: Mapping[str, pd.DataFrame], run: int | None, seconds: float | None = None
) -> dict[str, pd.DataFrame]:
    """The rows of ``run`` (every row when None) up to the last time every source recorded
    (a deployment may record its trajectories for the first minutes only), and of those the
    first ``seconds``; sources without such rows are left out."""
    d = {name: df if run is None else df[df["run"] == run] for name, df in sources.items()}
    d = {name: df for name, df in d.items() if len(df)}
    if not d:
        raise ValueError(
            "time-space data: no rows to plot"
            if run is None
            else f"no trajectory of run {run} to plot"
        )
    end = min(float(df["time_s"].max()) for df in d.values())
    if seconds is not None:
        end = min(end, min(float(df["time_s"].min()) for df in d.values()) + seconds)
    return {name: df[df["time_s"] <= end + 1e-9] for name, df in d.items()}


def lane_figure(
    d: Mapping[str, pd.DataFrame],
    path: Path | str,
    title: str,
    cmap: Colormap,
    draw: Callable[[Axes, pd.DataFrame, Normalize], None],
) -> Path:
    """A figure with a row per lane (0 = rightmost) and a column per source, one speed
    scale: ``draw(ax, rows, norm)`` fills each cell with its source's rows on its lane."""
    lane_ids = sorted({int(x) for df in d.values() for x in df["lane_index"].unique()})
    v = np.concatenate([df["speed_mps"].to_numpy(float) for df in d.values()])
    norm = Normalize(float(np.nanmin(v)), float(np.nanmax(v)) + 1e-6)
    fig = Figure(figsize=(4.0 * len(d) + 1.2, 3.0 * len(lane_ids) + 0.8), layout="constrained")
    axes = fig.subplots(len(lane_ids), len(d), squeeze=False, sharex=True, sharey=True)
    for j, (name, df) in enumerate(d.items()):
        axes[0, j].set_title(name)
        axes[-1, j].set_xlabel("time (s)")
        for i, lane in enumerate(lane_ids):
            draw(axes[i, j], df[df["lane_index"] == lane], norm)
    for i, lane in enumerate(lane_ids):
        axes[i, 0].set_ylabel(f"lane {lane}: position (m)")
    fig.suptitle(title)
    fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, label="speed (m/s)")
    return save_figure(fig, path)


def lane_segments(g: pd.DataFrame, max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Line segments (time, position) of every vehicle's consecutive rows on one lane, and
    their mean speeds; no segment across a lane change (a gap in time), a restart of time
    or the wrap of a loop (position going back)."""
    g = g.sort_values(["vehicle_id", "time_s"], kind="stable")
    t, x, v = (g[c].to_numpy(float) for c in ("time_s", "arc_m", "speed_mps"))
    same = g["vehicle_id"].to_numpy()[1:] == g["vehicle_id"].to_numpy()[:-1]
    dt, dx = np.diff(t), np.diff(x)
    keep = same & (dt > 0) & (dt <= max_dt_s) & (dx >= 0)
    pts = np.column_stack([t, x])
    return np.stack([pts[:-1], pts[1:]], axis=1)[keep], 0.5 * (v[:-1] + v[1:])[keep]


def plot_time_space(
    sources: Mapping[str, pd.DataFrame],
    path: Path | str,
    run: int | None = None,
    seconds: float | None = None,
    length_m: float | None = None,
    borders_m: Sequence[float] = (),
    title: str = "Time-space diagram per lane",
) -> Path:
    """Time-space diagram of any road: position against time, a line per vehicle coloured by
    speed, one row per lane (0 = rightmost) and one column per source (the ground truth
    beside each method), one speed scale.

    ``sources`` map a name to trajectories with the columns time_s, vehicle_id, arc_m,
    speed_mps, and lane_index (a road without it has one lane) and run where ``run`` picks
    one. The first ``seconds`` are drawn where every source recorded; ``length_m`` is the
    top of the position axis (the data's extent without it), ``borders_m`` are drawn dotted
    across it (edge borders).
    """
    for name, df in sources.items():
        _require(df, ["time_s", "vehicle_id", "arc_m", "speed_mps"], f"time-space data {name}")
    d = {k: df if "lane_index" in df else df.assign(lane_index=0) for k, df in sources.items()}
    cmap = mpl.colormaps[SPEED_CMAP]

    def draw(ax: Axes, g: pd.DataFrame, norm: Normalize) -> None:
        times = np.unique(g["time_s"].to_numpy(float))
        step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
        segs, speeds = lane_segments(g, 1.5 * step)
        if len(segs):
            lc = LineCollection(segs, cmap=cmap, norm=norm, linewidths=1.2)
            lc.set_array(speeds)
            ax.add_collection(lc)
        ax.autoscale_view()
        if length_m is not None:
            ax.set_ylim(0.0, length_m)
        for border in borders_m:
            ax.axhline(border, color="grey", lw=0.5, ls=":")
        ax.grid(alpha=0.3)

    title = title if run is None else f"{title}, run {run}"
    return lane_figure(window(d, run, seconds), path, title, cmap, draw)


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


# --------------------------------------------------------------------------- distributions


def plot_distributions(
    df: pd.DataFrame | Path | str,
    path: Path | str,
    reference: str = "ground_truth",
    by_k: bool = False,
    bins: int = 40,
) -> Path:
    """Speed and spacing histograms per method, overlaid as density steps.

    ``df`` has the columns method, K, speed_mps, spacing_m. The ``reference`` method is drawn
    thick and black. With ``by_k`` there is one row of panels per number of hidden vehicles
    K; reference rows whose K is missing appear in every row. Legends give mean and std.
    """
    df = _frame(df)
    _require(df, ["method", "K", "speed_mps", "spacing_m"], "distribution data")
    methods = list(dict.fromkeys(df["method"]))
    if reference in methods:  # reference first, so it is drawn under the others' legend
        methods = [reference] + [m for m in methods if m != reference]
    ks = sorted(df["K"].dropna().unique()) if by_k else [None]
    ks = ks or [None]
    columns = (
        ("speed_mps", "Speed", "speed (m/s)", "density (s/m)"),
        ("spacing_m", "Spacing", "spacing, front to front (m)", "density (1/m)"),
    )
    edges = {c[0]: np.histogram_bin_edges(df[c[0]].dropna(), bins=bins) for c in columns}
    fig = Figure(figsize=(12, 3.8 * len(ks)), layout="constrained")
    axes = fig.subplots(len(ks), 2, squeeze=False)
    for row, k in zip(axes, ks, strict=True):
        d = df if k is None else df[(df["K"] == k) | df["K"].isna()]
        for ax, (col, name, xlabel, ylabel) in zip(row, columns, strict=True):
            j = 0
            for method in methods:
                x = d.loc[d["method"] == method, col].dropna().to_numpy()
                if not x.size:
                    continue
                ref = method == reference
                color = REFERENCE_COLOR if ref else METHOD_COLORS[j % len(METHOD_COLORS)]
                j += 0 if ref else 1
                ax.hist(
                    x,
                    bins=edges[col],
                    density=True,
                    histtype="step",
                    color=color,
                    lw=2.8 if ref else 1.5,
                    zorder=3 if ref else 2,
                    label=f"{method}: mean {x.mean():.2f}, std {x.std():.2f}",
                )
            ax.set_ylim(0.0, ax.get_ylim()[1] * 1.4)  # head room for the legend
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.set_title(name if k is None else f"{name}, K = {int(k)} hidden vehicles")
            ax.legend(fontsize="small", loc="upper left")
            ax.grid(alpha=0.3)
    return save_figure(fig, path)


# --------------------------------------------------------------------------- training


def plot_generator_training(log: pd.DataFrame | Path | str, path: Path | str) -> Path:
    """Stage I: total generator loss (train and validation) and each L term per epoch."""
    df = _frame(log)
    _require(df, ["epoch", "train_loss", "val_loss"], "generator_train_log")
    fig = Figure(figsize=(12, 4.2), layout="constrained")
    ax_l, ax_t = fig.subplots(1, 2)
    ax_l.plot(df["epoch"], df["train_loss"], color="tab:blue", lw=2, label="train")
    ax_l.plot(df["epoch"], df["val_loss"], color="tab:red", lw=2, label="validation")
    best = df.loc[df["val_loss"].idxmin()]
    ax_l.axvline(
        best["epoch"], color="grey", ls=":", label=f"best validation: epoch {int(best['epoch'])}"
    )
    ax_l.set_title("Generator loss L_gen")
    ax_l.set_ylabel("loss (dimensionless)")
    terms = [c[len("train_") :] for c in df.columns if c.startswith("train_L")]
    for j, term in enumerate(terms):
        color = f"C{j}"
        ax_t.plot(df["epoch"], df[f"train_{term}"], color=color, lw=1.6, label=f"{term} train")
        if f"val_{term}" in df:
            ax_t.plot(
                df["epoch"],
                df[f"val_{term}"],
                color=color,
                lw=1.6,
                ls="--",
                label=f"{term} validation",
            )
    if terms and (df[[f"train_{t}" for t in terms]] > 0).all().all():
        ax_t.set_yscale("log")
    ax_t.set_title("Loss terms (solid: train, dashed: validation)")
    ax_t.set_ylabel("term value (dimensionless)")
    for ax in (ax_l, ax_t):
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small", ncols=2 if ax is ax_t else 1)
    return save_figure(fig, path)


POLICY_PANELS = (
    ("r_macro", "macro reward r_macro,t (per step, 0..1)", "reward (dimensionless)"),
    ("r_micro_per_pair", "micro log-likelihood per observed pair", "log-likelihood (nats)"),
    ("pg_loss", "policy-gradient loss", "loss (dimensionless)"),
    ("v_loss", "value loss", "loss (reward^2)"),
    ("kl", "approximate KL per update", "KL (nats)"),
    ("action_std_mps2", "action std of the policy", "std (m/s^2)"),
)


def plot_policy_training(log: pd.DataFrame | Path | str, path: Path | str) -> Path:
    """Stage II: PPO diagnostics per update (rewards, losses, KL, action std)."""
    df = _frame(log)
    _require(df, ["update", *(c for c, _, _ in POLICY_PANELS)], "policy_train_log")
    fig = Figure(figsize=(13, 6.5), layout="constrained")
    axes = fig.subplots(2, 3, sharex=True).ravel()
    for j, (ax, (col, title, ylabel)) in enumerate(zip(axes, POLICY_PANELS, strict=True)):
        ax.plot(df["update"], df[col], color=f"C{j}", lw=1.8)
        if col == "v_loss" and (df[col] > 0).all():
            ax.set_yscale("log")
        ax.set_title(title)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for ax in axes[3:]:
        ax.set_xlabel("PPO update")
    fig.suptitle("Policy training (PPO)")
    return save_figure(fig, path)
