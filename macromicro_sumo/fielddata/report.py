"""The data report of field data: what was read, kept, dropped and flagged, with plots.

``data_report`` returns the text of ``data_report.md`` and a table (``data_report.csv``)
with one row per file and vehicle or station: rows read, kept, dropped and why, rows
flagged. ``write_data_report`` writes both and two figures: raw against cleaned speeds
and accelerations of the vehicles with the most flags, and each station's flow and speed
over time. Figures use ``matplotlib.figure`` directly (the Agg canvas; no pyplot, no
display), as the report package does, which ranks above this one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from macromicro_sumo.fielddata.cleaning import CleanStations, CleanTrajectories
from macromicro_sumo.files import atomic_path, write_csv, write_text

DPI = 110
REPORT_COLUMNS = (
    "file",
    "layout",
    "kind",
    "id",
    "rows_read",
    "rows_kept",
    "rows_dropped",
    "dropped_reason",
    "accel_outliers",
    "speed_jumps",
    "gaps",
)


def _vehicle_rows(c: CleanTrajectories) -> pd.DataFrame:
    f = c.flags.groupby("vehicle_id", sort=True)
    per = pd.DataFrame(
        {
            "rows_kept": f.size(),
            "accel_outliers": f["accel_outlier"].sum(),
            "speed_jumps": f["speed_jump"].sum(),
            "gaps": f["after_gap"].sum(),
        }
    ).reset_index(names="id")
    out = per.assign(
        file=str(c.source.file),
        layout=c.source.layout,
        kind="vehicle",
        rows_read=per["rows_kept"],
        rows_dropped=0,
        dropped_reason="",
    )
    if c.source.dropped_off_section:
        out = pd.concat(
            [
                out,
                pd.DataFrame(
                    [
                        {
                            "file": str(c.source.file),
                            "layout": c.source.layout,
                            "kind": "vehicle",
                            "id": "(off the section)",
                            "rows_read": c.source.dropped_off_section,
                            "rows_kept": 0,
                            "rows_dropped": c.source.dropped_off_section,
                            "dropped_reason": "off the section",
                        }
                    ]
                ),
            ],
            ignore_index=True,
        )
    return out


def _station_rows(c: CleanStations) -> pd.DataFrame:
    read = c.source.frame.groupby(["detector_id", "lane_index"]).size().rename("rows_read")
    kept = c.frame.groupby(["detector_id", "lane_index"]).size().rename("rows_kept")
    why = (
        c.dropped.groupby(["detector_id", "lane_index"])["reason"]
        .agg(lambda r: "; ".join(f"{k}: {n}" for k, n in r.value_counts().items()))
        .rename("dropped_reason")
    )
    per = pd.concat([read, kept, why], axis=1).reset_index()
    per["rows_kept"] = per["rows_kept"].fillna(0).astype(int)
    ids = per["detector_id"].astype(str) + np.where(
        per["lane_index"] >= 0, " lane " + per["lane_index"].astype(str), " (all lanes)"
    )
    return per.assign(
        id=ids,
        file=str(c.source.file),
        layout=c.source.layout,
        kind="station",
        rows_dropped=per["rows_read"] - per["rows_kept"],
        dropped_reason=per["dropped_reason"].fillna(""),
        accel_outliers=0,
        speed_jumps=0,
        gaps=0,
    )


def leader_counts(c: CleanTrajectories) -> dict[str, int]:
    """Rows of a file with a measured leader (a vehicle ahead measured, or measured none),
    and rows of a layout that carries no leader measurement at all."""
    if not c.source.leader_measured:
        return {"leader_rows_measured": 0, "leader_rows_unmeasured": len(c.frame)}
    ahead = int(np.isfinite(c.frame["leader_spacing_m"].to_numpy(dtype=float)).sum())
    return {"leader_rows_measured": len(c.frame), "leader_rows_with_leader": ahead}


def leader_lines(trajectories: list[CleanTrajectories]) -> list[str]:
    """What the micro pairs' leaders are, per file; a warning for every file without a
    leader measurement (its pairs see the next observed vehicle as the leader)."""
    out = []
    for c in trajectories:
        n = leader_counts(c)
        if c.source.leader_measured:
            out.append(
                f"- {c.source.file.name}: leader measured by the vehicle in all "
                f"{n['leader_rows_measured']} rows ({n['leader_rows_with_leader']} with a "
                "vehicle ahead): micro pairs take it"
            )
        else:
            out.append(
                f"- **Warning**: {c.source.file.name} ({c.source.layout}) has no leader "
                f"measurement ({n['leader_rows_unmeasured']} rows): its micro pairs' leader is "
                "the next observed vehicle, with hidden vehicles possibly between "
                "(docs/field-data.md)"
            )
    return out + [""] if out else []


def data_report(
    trajectories: list[CleanTrajectories], stations: list[CleanStations]
) -> tuple[str, pd.DataFrame]:
    """(data_report.md text, per file/vehicle/station table of what was kept and dropped)."""
    parts = [_vehicle_rows(c) for c in trajectories] + [_station_rows(c) for c in stations]
    table = (
        pd.concat(parts, ignore_index=True)[list(REPORT_COLUMNS)]
        if parts
        else pd.DataFrame(columns=list(REPORT_COLUMNS))
    )
    lines = ["# Field data report", ""]
    if trajectories:
        lines += [
            "## Trajectories",
            "",
            "| file | layout | vehicles | rows | off the section | accel outliers | "
            "speed jumps | gaps | speed change by cleaning (RMS) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for c in trajectories:
            fl = c.flags
            change = float(np.sqrt(np.mean((c.frame["speed_mps"] - c.raw_speed_mps) ** 2)))
            lines.append(
                f"| {c.source.file.name} | {c.source.layout} | {fl['vehicle_id'].nunique()} | "
                f"{len(fl)} | {c.source.dropped_off_section} | {int(fl['accel_outlier'].sum())} | "
                f"{int(fl['speed_jump'].sum())} | {int(fl['after_gap'].sum())} | "
                f"{change:.3f} m/s |"
            )
        lines.append("")
        lines += leader_lines(trajectories)
    if stations:
        lines += [
            "## Stations",
            "",
            "| file | layout | stations | intervals read | kept | dropped | why |",
            "|---|---|---|---|---|---|---|",
        ]
        for c in stations:
            why = "; ".join(f"{k}: {n}" for k, n in c.dropped["reason"].value_counts().items())
            lines.append(
                f"| {c.source.file.name} | {c.source.layout} | "
                f"{c.source.frame['detector_id'].nunique()} | {len(c.source.frame)} | "
                f"{len(c.frame)} | {len(c.dropped)} | {why or '-'} |"
            )
        lines.append("")
    lines.append("Per vehicle and station: `data_report.csv`. Cleaning: docs/field-data.md.")
    return "\n".join(lines) + "\n", table


def _save(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path


def plot_cleaning(c: CleanTrajectories, path: Path, n_vehicles: int = 4) -> Path:
    """Raw against cleaned speed and acceleration of the vehicles with the most flags (the
    longest trajectories where none is flagged)."""
    fl = c.flags.assign(n=c.flags[["accel_outlier", "speed_jump", "after_gap"]].sum(axis=1))
    rank = fl.groupby("vehicle_id").agg(n=("n", "sum"), rows=("n", "size"))
    pick = rank.sort_values(["n", "rows"], ascending=False).index[:n_vehicles]
    fig = Figure(figsize=(9, 2.4 * len(pick) + 0.4), layout="constrained")
    axes = fig.subplots(len(pick), 2, squeeze=False)
    raw_a = np.zeros(len(c.frame))
    for idx in c.frame.groupby("vehicle_id").indices.values():
        if len(idx) > 1:
            raw_a[idx] = np.gradient(c.raw_speed_mps[idx], c.frame["time_s"].to_numpy()[idx])
    for row, vid in zip(axes, pick, strict=True):
        k = np.flatnonzero((c.frame["vehicle_id"] == vid).to_numpy())
        t = c.frame["time_s"].to_numpy()[k]
        row[0].plot(t, c.raw_speed_mps[k], lw=0.8, color="0.6", label="file")
        row[0].plot(t, c.frame["speed_mps"].to_numpy()[k], lw=1.3, label="cleaned")
        row[1].plot(t, raw_a[k], lw=0.8, color="0.6", label="file speeds, differenced")
        row[1].plot(t, c.frame["accel_mps2"].to_numpy()[k], lw=1.3, label="cleaned")
        row[0].set_ylabel(f"{vid}\nspeed [m/s]")
        row[1].set_ylabel("accel. [m/s²]")
    axes[0, 0].legend(fontsize=7)
    axes[0, 1].legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    fig.suptitle(f"{c.source.file.name}: raw and cleaned signals")
    return _save(fig, path)


def plot_stations(c: CleanStations, path: Path) -> Path:
    """Flow and speed of every station over time (lanes summed / flow-weighted), kept
    intervals as lines, dropped ones as crosses on the time axis."""
    f = c.frame.assign(q_v=c.frame["flow_vph"] * c.frame["speed_mps"].fillna(0.0))
    per = f.groupby(["arc_m", "begin_s"]).agg(flow=("flow_vph", "sum"), qv=("q_v", "sum"))
    per["speed"] = per["qv"] / per["flow"].where(per["flow"] > 0)
    fig = Figure(figsize=(9, 5), layout="constrained")
    ax_q, ax_v = fig.subplots(2, 1, sharex=True)
    for arc, grp in per.reset_index().groupby("arc_m"):
        ax_q.plot(grp["begin_s"], grp["flow"], lw=1, label=f"{arc:.0f} m")
        ax_v.plot(grp["begin_s"], grp["speed"], lw=1)
    if len(c.dropped):
        ax_q.plot(c.dropped["begin_s"], np.zeros(len(c.dropped)), "x", color="red", label="dropped")
    ax_q.set_ylabel("flow [veh/h]")
    ax_v.set_ylabel("speed [m/s]")
    ax_v.set_xlabel("interval start [s]")
    ax_q.legend(fontsize=6, ncol=4)
    fig.suptitle(f"{c.source.file.name}: station time series")
    return _save(fig, path)


def write_data_report(
    out: Path, trajectories: list[CleanTrajectories], stations: list[CleanStations]
) -> list[Path]:
    """``data_report.md``, ``data_report.csv`` and the figures, written into ``out``."""
    out = Path(out)
    text, table = data_report(trajectories, stations)
    write_text(text, out / "data_report.md")
    write_csv(table, out / "data_report.csv")
    paths = [out / "data_report.md", out / "data_report.csv"]
    for i, c in enumerate(trajectories):
        paths.append(plot_cleaning(c, out / f"data_trajectories_{i}.png"))
    for i, s in enumerate(stations):
        paths.append(plot_stations(s, out / f"data_stations_{i}.png"))
    return paths
