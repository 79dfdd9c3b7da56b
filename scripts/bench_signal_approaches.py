"""Where the hidden count's error sits on a signalised section's interval record: per signal
approach, its true constant against each lower bound ``signal_counts.approach_count`` takes
the largest of, and the error left with the true constant (the within-interval spread of the
counts); per snapshot, the error of each part (the counted approaches, the stretch past the
last signal, the rest on the density estimate).

An approach's count is a constant plus the up station's count less the stop bar's
(``truth.signal_counts``). Its true constant here is the median over the snapshots of the
true count less that difference; ``spread`` is the mean absolute error that is left with it
(what no constant can remove); ``density``, ``queue``, ``moving`` and ``empty`` are each
bound's constant less the true one (``density_constant``, ``queue_constant``, the median of
the free-travel count, count >= 0 at the first bound: exact from an empty road).

``--junction-counts`` adds, beside the parts, the junction stretches' error counted from
their stop bars' counts timed by the programs (``truth.junction_counts``: ``junctions``)
and that of the interval density the rest holds on them (``junction_density``); the parts
and their sum are unchanged. ``--levels`` splits the rest by where it lies (``REST_PARTS``: the
junction stretches from a stop bar to the first station past its line, the ends beyond the
outermost stations, the other stretches) and each part's error into its level (the
interval's mean estimate less the interval's mean truth over its snapshots) and its shape
(the rest: where within the interval the snapshot falls); ``level_summary`` tables them per
net and regime. A ground truth is ``simulate``'s folder (its scenario beside it) or a
run's ``ground_truth`` (its scenario named by the run's manifest).

    .venv/bin/python scripts/bench_signal_approaches.py --start-s 240 \\
        --out /tmp/approaches GT_DIR ...       # a ground truth (``simulate``) per argument
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_hidden_count import SLOW_MPS, SLOW_SHARE, read_truth  # noqa: E402

from macromicro_sumo.data.section import at_snapshot_times  # noqa: E402
from macromicro_sumo.road.leaders import STANDING_MIN_GAP_M  # noqa: E402
from macromicro_sumo.road.section import Section  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.sumo.inputs import read_net, scenario_inputs  # noqa: E402
from macromicro_sumo.truth import signal_counts as sc  # noqa: E402
from macromicro_sumo.truth.hidden_count import window_mean  # noqa: E402
from macromicro_sumo.truth.interval_counts import effective_densities  # noqa: E402
from macromicro_sumo.truth.junction_counts import junction_pieces  # noqa: E402
from macromicro_sumo.truth.section_macro import (  # noqa: E402
    cut_at_lines,
    integrate_stations,
    loop_lengths_m,
    station_density,
)
from macromicro_sumo.truth.signal_lines import stop_lines  # noqa: E402
from macromicro_sumo.truth.standing import jam_spacing_m  # noqa: E402
from macromicro_sumo.truth.stations import (  # noqa: E402
    full_stations,
    side_junction_arcs,
    station_speeds,
)

NEAR_M = 20.0
"""The true density at a station: the vehicles within this either side of it."""

REST_PARTS = ("junctions", "up_end", "down_end", "other")
"""Where the rest (the density estimate) lies: from a stop bar over its junction to the first
full station past the line, before the first full station, past the last one, elsewhere."""

STANDING_FRONT_M = 1.0
"""How far before its stop line SUMO's first standing vehicle's front stands (measured on
arterial 818's entry and drawn 565's second approach: the median 1.0 m, and the fronts behind
it at 1.0 m plus a whole number of jam spacings, 170 m back)."""

BANDS_M = (-1.0, 5.0, 25.0, 80.0, np.inf)
BAND_NAMES = ("stop bar", "bar to 25 m", "25-80 m", "farther or none")
"""Station bands by the distance to the next stop line ahead (m)."""


def scenario_file(gt: Path) -> Path:
    """The scenario of the ground truth ``gt``: the bench's ``scenario.toml`` beside it, else
    the one the manifest of the run holding it names (``macromicro run``'s ``ground_truth``),
    else the one its own manifest names (``simulate SCENARIO --out GT`` anywhere)."""
    toml = gt.parent / "scenario.toml"
    if toml.is_file():
        return toml
    run = gt.parent / "manifest.json"
    return Path(
        json.loads((run if run.is_file() else gt / "manifest.json").read_text())["scenario_file"]
    )


def truth_name(gt: Path) -> str:
    """The net a ground truth stands for: a run's folder (``macromicro run``'s
    ``ground_truth``), else the bench's net folder above it (``arterial_NNN/<variant>/gt``,
    ``.../<variant>/occupancy_loop_2m/gt``), else the folder above the scenario's."""
    if gt.name == "ground_truth":
        return gt.parent.name
    nets = [p.name for p in gt.parents if p.name.startswith(("arterial_", "seed_"))]
    return nets[0] if nets else gt.parent.parent.name


def rest_spans(
    arcs: np.ndarray, lines: list[float], covered: list[tuple[float, float]], length_m: float
) -> dict[str, list[tuple[float, float]]]:
    """The section's stretches outside the counted pieces (``covered``) by ``REST_PARTS``,
    cut at the full stations ``arcs`` (ascending) and the pieces' ends."""
    ends = [x for span in covered for x in span]
    cuts = sorted({0.0, float(length_m), *map(float, arcs), *ends})
    out: dict[str, list[tuple[float, float]]] = {name: [] for name in REST_PARTS}
    for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
        mid = 0.5 * (lo + hi)
        if hi - lo < 1e-6 or any(a <= mid < b for a, b in covered):
            continue
        if mid < arcs[0]:
            out["up_end"].append((lo, hi))
        elif mid >= arcs[-1]:
            out["down_end"].append((lo, hi))
        else:
            below, above = arcs[arcs <= mid].max(), arcs[arcs > mid].min()
            over = any(below < line <= above for line in lines)
            out["junctions" if over else "other"].append((lo, hi))
    return out


def level_rows(
    d: pd.DataFrame,
    section: Section,
    lines: list[float],
    pieces: dict,
    snaps: pd.DataFrame,
    times: np.ndarray,
    window_s: float,
) -> pd.DataFrame:
    """Per snapshot of one run: each counted piece's and each rest part's (``rest_spans``)
    error, and its level (the interval's mean estimate less the interval's mean truth over
    its snapshots, the interval being the one holding the snapshot)."""
    covered = [span for piece in pieces.values() for span in piece.arcs_m]
    spans = rest_spans(full_stations(d, section), lines, covered, section.length_m)
    cut = lines if (loop_lengths_m(d) > 0).any() else []
    dens = []
    for (begin, end), e1 in d[d["kind"] == "e1"].groupby(["begin_s", "end_s"], sort=True):
        per_station = cut_at_lines(station_density(e1, section), cut)
        row = {"begin_s": begin, "end_s": end}
        for name, parts in spans.items():
            row[name] = sum(integrate_stations(per_station, section, lo, hi) for lo, hi in parts)
        dens.append(row)
    dens = pd.DataFrame(dens)
    arcs_at = {t: x["arc_m"].to_numpy() for t, x in snaps.groupby("time_s")}

    def on(t: float, parts) -> float:
        a = arcs_at[t]
        return float(sum(((a >= lo) & (a < hi)).sum() for lo, hi in parts))

    rows = pd.DataFrame({"time_s": times})
    rows["interval"] = np.searchsorted(dens["begin_s"].to_numpy(), times, "right") - 1
    for name, piece in pieces.items():
        rows[f"{name}_est"] = piece.vehicles
        rows[f"{name}_true"] = [on(t, piece.arcs_m) for t in times]
    for name, parts in spans.items():
        rows[f"{name}_est"] = [window_mean(dens, name, t, window_s) for t in times]
        rows[f"{name}_true"] = [on(t, parts) for t in times]
    for name in [*pieces, *spans]:
        est, true = rows.pop(f"{name}_est"), rows.pop(f"{name}_true")
        by = rows["interval"]
        rows[name] = est - true
        rows[f"{name}_level"] = est.groupby(by).transform("mean") - true.groupby(by).transform(
            "mean"
        )
    return rows.drop(columns="interval")


def level_summary(levels: pd.DataFrame) -> pd.DataFrame:
    """Per net (``truth``) and regime, and over all: each part's bias per lane, its level
    and its shape (bias less level), over the snapshots the estimate covers (the rest's
    interval density exists: ``k_estimates`` skips the others)."""
    levels = levels[np.isfinite(levels["rest"])]
    names = [c for c in ("approaches", "exit", *REST_PARTS) if c in levels]
    out = pd.DataFrame(index=levels.index)
    for c in names:
        out[c] = levels[c].fillna(0.0) / levels["lanes"]
        out[f"{c} level"] = levels[f"{c}_level"].fillna(0.0) / levels["lanes"]
        out[f"{c} shape"] = out[c] - out[f"{c} level"]
    keys = [levels["truth"], levels["congested"]]
    table = out.groupby(keys).mean()
    every = out.groupby(levels["congested"]).mean()
    every.index = pd.MultiIndex.from_product([["all"], every.index])
    return pd.concat([table, every]).round(2)


def approach_rows(
    gt: Path,
    start_s: float = 0.0,
    junctions: bool = False,
    levels: bool = False,
    near_line: bool | str = False,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(one row per run and approach: the constants' errors, which bound is the largest,
    vehicles; one row per snapshot: each part's error, vehicles) of the ground truth ``gt``
    scored from ``start_s`` on; ``junctions``: the junction stretches' errors, counted and by
    the rest's density, too; ``levels``: each part's and each rest part's error and level
    (``level_rows``); ``near_line``: the approaches counted so (``approach_count``)."""
    man = json.loads((gt / "manifest.json").read_text())["scenario"]
    section = Section.read(gt / "section.json")
    traj, det, _ = read_truth(gt, start_s)
    det = det.assign(k_point_vpkm=effective_densities(det))
    net_file = scenario_inputs(load_scenario(scenario_file(gt))).net_file
    side = side_junction_arcs(read_net(net_file), section)
    lines = stop_lines(net_file, section)
    snaps = at_snapshot_times(traj, man["generator"]["snapshot_every_s"])
    window = man["detectors"]["k_window_s"]
    lanes_mean = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    rows, parts = [], []
    for run, g in snaps.groupby("run"):
        d = det[det["run"] == run]
        times = np.sort(g["time_s"].unique())
        arcs_at = {t: x["arc_m"].to_numpy() for t, x in g.groupby("time_s")}
        spacing = sc.standing.jam_spacing_m(d)
        for i, a in enumerate(sc.approaches(d, section, lines, side)):
            true = np.array(
                [((arcs_at[t] >= a.up_m) & (arcs_at[t] < a.bar_m)).sum() for t in times]
            )

            def io(x: np.ndarray, a: sc.Approach = a, d: pd.DataFrame = d) -> np.ndarray:
                return sc.arrivals(d, a, x) - sc.cumulative(d, a.bar_m, x, a.line)

            io_t = io(times)
            c_true = float(np.median(true - io_t))
            begin, end, _ = sc.station_counts(d, a.bar_m)
            e = section.edge_index(np.array([a.bar_m]))[0]
            lanes = int(section.n_lanes[e])
            travel = (a.bar_m - a.up_m) / float(np.nanmax(section.limits_mps[e]))
            bounds = np.concatenate([begin, end[-1:]])
            tb = bounds[bounds >= begin[0] + travel]
            moving = sc.arrivals(d, a, tb) - sc.arrivals(d, a, tb - travel)
            est = sc.approach_count(d, section, a, times, spacing, near_line)
            bound = {
                "density": sc.density_constant(d, section, a, io) - c_true,
                "queue": sc.queue_constant(d, section, a, io, spacing) - c_true,
                "moving": float(np.quantile(moving - io(tb), sc.CLEAR_QUANTILE)) - c_true,
                "empty": -float(io(bounds).min()) - c_true,
            }
            rows.append(
                {
                    "truth": truth_name(gt),
                    "run": run,
                    "approach": i,
                    "up_m": a.up_m,
                    "bar_m": a.bar_m,
                    "lanes": lanes,
                    "entry": a.before is None,
                    "true_vehicles": float(true.mean()),
                    "room": lanes * (a.bar_m - a.up_m) / spacing,
                    "true_constant": c_true,
                    "spread": float(np.abs(true - io_t - c_true).mean()),
                    **bound,
                    "bound": max(bound, key=bound.get),
                    "near_line": sc.density_constant(d, section, a, io, spacing) - c_true,
                    "error": float(np.abs(est - true).mean()) if est is not None else np.nan,
                    "bias": float((est - true).mean()) if est is not None else np.nan,
                }
            )
        pieces, rest = sc.approach_pieces(d, section, lines, side, run, times, near_line)
        more, less = (
            junction_pieces(d, section, lines, run, times, rest) if junctions else ({}, rest)
        )
        on_junctions = rest.assign(vehicles=rest["vehicles"] - less["vehicles"])
        line_arcs = [line.arc_m for line in lines]
        split = level_rows(d, section, line_arcs, pieces, g, times, window) if levels else None
        for k, t in enumerate(times):
            arcs = arcs_at[t]
            slow = (g.loc[g["time_s"] == t, "speed_mps"] <= SLOW_MPS).mean() >= SLOW_SHARE
            row = {"truth": truth_name(gt), "run": run, "time_s": t}
            row |= {"congested": bool(slow), "lanes": lanes_mean}
            inside = np.zeros(len(arcs), bool)
            for name, piece in pieces.items():
                on = np.zeros(len(arcs), bool)
                for lo, hi in piece.arcs_m:
                    on |= (arcs >= lo) & (arcs < hi)
                inside |= on
                row[name] = float(piece.vehicles[k] - on.sum())
            row["rest"] = window_mean(rest, "vehicles", t, window) - float((~inside).sum())
            for piece in more.values():  # beside the parts: the rest still holds them
                on = np.zeros(len(arcs), bool)
                for lo, hi in piece.arcs_m:
                    on |= (arcs >= lo) & (arcs < hi)
                row["junctions"] = float(piece.vehicles[k] - on.sum())
                dens = window_mean(on_junctions, "vehicles", t, window)
                row["junction_density"] = dens - float(on.sum())
            if split is not None:
                row |= split.iloc[k].drop("time_s").to_dict()
            parts.append(row)
    return pd.DataFrame(rows), pd.DataFrame(parts)


def station_rows(gt: Path, start_s: float = 0.0) -> pd.DataFrame:
    """One row per run, interval and station of the ground truth ``gt`` from ``start_s``:
    its distance to the next stop line ahead (``to_line_m``, inf past the last) and band,
    its interval speed, its density as the count reads it (``station_density``) and the
    true one (the trajectories' vehicles within ``NEAR_M`` either side, over the
    interval's samples), both per lane in veh/km, and ``standing``: where the loop falls in
    the red's standing queue, "under a car" or "in a gap" ("past the last line"). SUMO's
    equal cars stand at fixed places (fronts ``STANDING_FRONT_M`` plus a whole number of
    jam spacings, ``standing.jam_spacing_m``, before the line), so a point loop under one
    reads occupancy over the car's length (1 / 5 m where the queue stands: 200 veh/km
    per lane against 133) and one in a gap reads nothing while it stands."""
    section = Section.read(gt / "section.json")
    traj, det, _ = read_truth(gt, start_s)
    det = det.assign(k_point_vpkm=effective_densities(det))
    net_file = scenario_inputs(load_scenario(scenario_file(gt))).net_file
    lines = np.array([line.arc_m for line in stop_lines(net_file, section)])
    spacing = {run: jam_spacing_m(d) for run, d in det.groupby("run")}
    rows = []
    for (run, begin, end), e1 in det[det["kind"] == "e1"].groupby(["run", "begin_s", "end_s"]):
        x = traj[(traj["run"] == run) & (traj["time_s"] >= begin) & (traj["time_s"] < end)]
        samples = x["time_s"].nunique()
        if samples == 0:
            continue
        k, v, arcs = station_density(e1, section), station_speeds(e1), x["arc_m"].to_numpy()
        for arc, est in k.items():
            ahead = lines[lines >= arc]
            lanes = int(section.n_lanes[section.edge_index(np.array([arc]))[0]])
            near = ((arcs >= arc - NEAR_M) & (arcs < arc + NEAR_M)).sum() / samples
            to_line = float(ahead[0] - arc) if len(ahead) else np.inf
            lattice = np.mod(to_line - STANDING_FRONT_M, spacing[run]) if len(ahead) else 0.0
            car = spacing[run] - STANDING_MIN_GAP_M  # the car over the loop from its front
            rows.append(
                {
                    "truth": truth_name(gt),
                    "run": run,
                    "begin_s": begin,
                    "arc_m": arc,
                    "to_line_m": to_line,
                    "speed_mps": float(v.get(arc, np.nan)),
                    "est_vpkm": float(est) / lanes,
                    "true_vpkm": float(near) / (2.0 * NEAR_M / 1000.0) / lanes,
                    "standing": "past the last line"
                    if not len(ahead)
                    else ("under a car" if lattice < car else "in a gap"),
                }
            )
    out = pd.DataFrame(rows)
    out["band"] = pd.cut(out["to_line_m"], BANDS_M, labels=BAND_NAMES)
    return out


def station_summary(stations: pd.DataFrame) -> pd.DataFrame:
    """Per band and place in the standing queue (``station_rows``' ``standing``): stations'
    intervals, mean interval speed, mean read and true density."""
    g = stations.groupby(["band", "standing"], observed=True)
    return pd.DataFrame(
        {
            "intervals": g.size(),
            "speed_mps": g["speed_mps"].mean(),
            "est_vpkm": g["est_vpkm"].mean(),
            "true_vpkm": g["true_vpkm"].mean(),
        }
    ).round(1)


def part_summary(parts: pd.DataFrame) -> pd.DataFrame:
    """Mean absolute error and bias per lane of each part, free / congested, over the
    snapshots the estimate covers (the rest's interval density exists: ``k_estimates``
    skips the others)."""
    parts = parts[np.isfinite(parts["rest"])]
    cols = [c for c in ("approaches", "exit", "rest") if c in parts]
    aside = [c for c in ("junctions", "junction_density") if c in parts]
    out = {}
    for c in cols + aside:  # aside: the junction stretches, also in the rest
        per_lane = parts[c] / parts["lanes"]
        out[f"{c} abs"] = per_lane.abs().groupby(parts["congested"]).mean()
        out[f"{c} bias"] = per_lane.groupby(parts["congested"]).mean()
    total = parts[cols].fillna(0.0).sum(axis=1) / parts["lanes"]
    out["all abs"] = total.abs().groupby(parts["congested"]).mean()
    return pd.DataFrame(out).round(2)


def main(args: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("truths", type=Path, nargs="+", help="ground-truth folders (simulate --out)")
    p.add_argument("--start-s", type=float, default=0.0, help="score from this time on (s)")
    p.add_argument("--out", type=Path, default=None, help="write approaches.csv, parts.csv")
    p.add_argument(
        "--junction-counts",
        action="store_true",
        help="also the junction stretches' error from their stop bars' counts timed by the "
        "programs and from the rest's density (a diagnostic: not added to the parts)",
    )
    p.add_argument(
        "--levels",
        action="store_true",
        help="also the rest split into junction stretches, ends and other stretches, and each "
        "part's error split into its level (interval mean) and shape (within the interval)",
    )
    p.add_argument(
        "--stations",
        action="store_true",
        help="also each station's read density against the true one within 20 m, by its "
        "distance to the next stop line (stations.csv)",
    )
    p.add_argument(
        "--near-line",
        nargs="?",
        const=True,
        default=False,
        choices=["all", "station"],
        help="count the approaches with the near-line loops' standing queue where the "
        "free-travel bound is the largest (truth.standing; StationRecord.near_line); all: half of "
        "it on every approach (standing.NEAR_LINE_ALL_SHARE); station: on every approach, what "
        "each near-line station's loops missed of it (standing.seen_share)",
    )
    o = p.parse_args(args)
    both = [
        approach_rows(gt, o.start_s, o.junction_counts, o.levels, o.near_line) for gt in o.truths
    ]
    rows = pd.concat([r for r, _ in both], ignore_index=True)
    parts = pd.concat([x for _, x in both], ignore_index=True)
    with pd.option_context("display.width", 250, "display.max_rows", 1000):
        print(rows.round(2).to_string(index=False))
        print(part_summary(parts).to_string())
        if o.levels:
            print(level_summary(parts).to_string())
    if o.stations:
        stations = pd.concat([station_rows(gt, o.start_s) for gt in o.truths], ignore_index=True)
        print(station_summary(stations).to_string())
        if o.out is not None:
            o.out.mkdir(parents=True, exist_ok=True)
            stations.to_csv(o.out / "stations.csv", index=False)
    if o.out is not None:
        o.out.mkdir(parents=True, exist_ok=True)
        rows.to_csv(o.out / "approaches.csv", index=False)
        parts.to_csv(o.out / "parts.csv", index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
