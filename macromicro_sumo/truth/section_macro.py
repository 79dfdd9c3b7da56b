"""Macro statistics of a section's ground truth: as its detectors estimate them and from
the full trajectories (what the simulation knows), and the summary of the hidden-count
estimate's error (the estimate itself: ``truth/hidden_count.py``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.data.macro import passage_spacings
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.density import (
    DEFAULT_VEHICLE_LENGTH_M,
    effective_length_m,
    occupancy_density,
    point_density,
    profile_integral,
)


def station_cells(arcs: np.ndarray, section: Section) -> np.ndarray:
    """Arc length each detector station stands for: the section split half-way between
    stations (around the loop on a closed section)."""
    order = np.argsort(arcs)
    a = arcs[order]
    if len(a) == 1:
        cells = np.array([section.length_m])
    elif section.closed:
        gaps = np.diff(np.concatenate([a, [a[0] + section.length_m]]))
        cells = 0.5 * (gaps + np.roll(gaps, 1))
    else:
        mids = np.concatenate([[0.0], 0.5 * (a[1:] + a[:-1]), [section.length_m]])
        cells = np.diff(mids)
    out = np.empty_like(cells)
    out[order] = cells
    return out


def loop_densities(det: pd.DataFrame, passages: pd.DataFrame) -> np.ndarray:
    """Each E1 row's density (veh/km, ``density.point_density``: flow / harmonic speed in
    free flow, occupancy / (vehicle + loop length) where speeds collapse); E2 rows keep
    theirs.

    The vehicle length is the mean of the loop's own passages in that run (its traffic's
    mix of cars and trucks), else of every loop's in the run, else SUMO's passenger car.
    """
    out = det["density_vpkm"].to_numpy(dtype=float).copy()
    e1 = (det["kind"] == "e1").to_numpy()
    if not e1.any():
        return out
    length = np.full(len(det), DEFAULT_VEHICLE_LENGTH_M)
    if len(passages):
        ids = passages["detector_id"].str.removeprefix("i_")
        per_loop = passages.groupby([passages["run"], ids])["length_m"].mean()
        per_run = passages.groupby("run")["length_m"].mean()
        keys = pd.MultiIndex.from_arrays([det["run"], det["detector_id"]])
        own = per_loop.reindex(keys).to_numpy()
        run_mean = per_run.reindex(det["run"]).to_numpy()
        length = np.where(np.isfinite(own), own, np.where(np.isfinite(run_mean), run_mean, length))
    k = point_density(
        det["flow_vph"].to_numpy(dtype=float),
        det["speed_mps"].to_numpy(dtype=float),
        det["occupancy_pct"].to_numpy(dtype=float),
        length,
        loop_lengths_m(det),
    )
    out[e1] = k[e1]
    return out


def loop_lengths_m(det: pd.DataFrame) -> np.ndarray:
    """Each row's occupancy loop length (m): an E1 row's ``length_m`` (0 for a point loop, the
    occupancy loop's with ``detectors.auto_occupancy_loop_m``); 0 where the table has none
    (field data)."""
    if "length_m" not in det:
        return np.zeros(len(det))
    e1 = (det["kind"] == "e1").to_numpy()
    return np.where(e1, np.nan_to_num(det["length_m"].to_numpy(dtype=float)), 0.0)


def run_vehicle_lengths(det: pd.DataFrame) -> np.ndarray:
    """Each E1 row's effective vehicle length (m, the loop's own length held): its run's
    median over the loops of theirs (``density.effective_length_m``); SUMO's passenger car
    plus the loop's length where no loop of the run flowed freely."""
    cols = ["flow_vph", "speed_mps", "occupancy_pct"]
    per_loop = det.groupby(["run", "detector_id"])[cols].apply(
        lambda g: effective_length_m(*(g[c].to_numpy(dtype=float) for c in cols), np.nan)
    )
    run = per_loop.groupby(level="run").median().reindex(det["run"]).to_numpy(dtype=float)
    # The calibrated length holds the loop's own; the passenger car's does not.
    return np.where(np.isfinite(run), run, DEFAULT_VEHICLE_LENGTH_M + loop_lengths_m(det))


def edie_densities(e1: pd.DataFrame) -> pd.DataFrame:
    """``e1`` (E1 rows with ``k_point_vpkm``) with each dual loop's density its occupancy
    over the run's effective length (``run_vehicle_lengths``) at any speed: Edie's, which
    counts a vehicle standing over the loop at red; flow / speed, which the blend takes
    above ``density.SPEED_OCCUPANCY_BELOW_MPS``, misses it (the crawl past a stop bar is
    at 8-10 m/s). Point loops keep theirs (their occupancy is SUMO's per-step sample)."""
    dual = loop_lengths_m(e1) > 0
    occ = occupancy_density(e1["occupancy_pct"].to_numpy(dtype=float), run_vehicle_lengths(e1))
    return e1.assign(k_point_vpkm=np.where(dual, occ, e1["k_point_vpkm"].to_numpy(dtype=float)))


def station_density(e1: pd.DataFrame, section: Section) -> pd.Series:
    """Density over all lanes (veh/km) of each station (arc) in one interval: the mean of
    its lanes that reported times the lanes of its edge. A lane with no row or no finite
    value is thereby imputed from the station's other lanes; a station with none drops
    out and its neighbours' densities are interpolated over it."""
    k = e1["k_point_vpkm"]
    ok = np.isfinite(k)
    per_lane = k[ok].groupby(e1.loc[ok, "arc_m"]).mean()
    lanes = section.n_lanes[section.edge_index(per_lane.index.to_numpy(dtype=float))]
    return per_lane * lanes


LINE_CUT_M = 0.01
"""How far past a stop line ``cut_at_lines`` puts the station that starts the next stretch."""


def cut_at_lines(per_station: pd.Series, lines_m: list[float]) -> pd.Series:
    """``per_station`` (``station_density``) with a station 1 cm past each stop line of
    ``lines_m`` that reads as the first station downstream of it with a value: the density
    steps at the line rather than running linearly from the stop bar's queue over the
    junction to the station past it (a queue's density there over-counts the junction
    stretch; it needs a stop bar that reads the queue: ``detectors.auto_occupancy_loop_m``)."""
    arcs = per_station.index.to_numpy(dtype=float)
    ok = np.isfinite(per_station.to_numpy(dtype=float))
    add = {}
    for line in lines_m:
        after = np.flatnonzero(ok & (arcs > line + LINE_CUT_M))
        if len(after):
            add[line + LINE_CUT_M] = float(per_station.iloc[after[0]])
    if not add:
        return per_station
    return pd.concat([per_station, pd.Series(add)]).sort_index()


def e2_covered_density(e2: pd.DataFrame, section: Section) -> float:
    """Density per lane (veh/km) of one interval's lane-area (E2) detectors over the
    lane-metres they cover, each covered metre once: where detectors overlap, the mean of
    theirs. A mean over the detectors by their lengths counts an overlap twice (two E2s that
    share 50 m of a lane put its density in twice) and so leans towards it; over the covered
    metres a tiling of the section reads its vehicles exactly whatever the density along it.
    A detector runs ``length_m`` along the arc from ``arc_m`` on its lane index of each edge
    it crosses (past the closing point of a loop, on from its start; junctions are not
    covered). No covered metre (no finite density): their mean by length."""
    pieces: dict[tuple[int, int], list[tuple[float, float, float]]] = {}
    cols = ["arc_m", "length_m", "lane_index", "density_vpkm"]
    shifts = (0.0, -section.length_m) if section.closed else (0.0,)
    for a0, length, lane, k in e2[cols].itertuples(index=False):
        if not (np.isfinite(k) and length > 0):
            continue
        for e, shift in ((e, x) for e in range(len(section.edge_ids)) for x in shifts):
            lo = max(float(a0) + shift, float(section.offsets_m[e]))
            hi = min(float(a0 + length) + shift, float(section.offsets_m[e] + section.lengths_m[e]))
            if hi > lo and int(lane) < int(section.n_lanes[e]):
                pieces.setdefault((e, int(lane)), []).append((lo, hi, float(k)))
    covered_m = vehicles_km = 0.0
    for spans in pieces.values():
        cuts = np.unique([x for lo, hi, _ in spans for x in (lo, hi)])
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            k = [kk for a, b, kk in spans if a <= lo and b >= hi]
            if k:
                covered_m += hi - lo
                vehicles_km += float(np.mean(k)) * (hi - lo)
    if covered_m > 0:
        return vehicles_km / covered_m
    ok = np.isfinite(e2["density_vpkm"]) & (e2["length_m"] > 0)
    if not ok.any():
        return float("nan")
    return float(np.average(e2.loc[ok, "density_vpkm"], weights=e2.loc[ok, "length_m"]))


def integrate_stations(
    per_station: pd.Series, section: Section, lo_m: float = 0.0, hi_m: float | None = None
) -> float:
    """Vehicles on [lo_m, hi_m] of the section from the stations' densities."""
    return profile_integral(
        per_station.index.to_numpy(dtype=float),
        per_station.to_numpy(dtype=float),
        section.length_m,
        section.closed,
        lo_m,
        hi_m,
    )


def detector_macro(
    det: pd.DataFrame,
    passages: pd.DataFrame,
    warmup_s: float,
    min_spacing_m: float,
    section: Section,
) -> pd.DataFrame:
    """Macro statistics per run and interval as the section's detectors estimate them.

    Speed: space-mean (E2 weighted by time on the detector; E1 the harmonic mean of the
    loops' speeds weighted by their counts times the arc their station stands for,
    ``station_cells``: sum q L / sum (q L / v), the section's vehicles' mean speed). Weighted
    by counts alone, the stations 15 m inside each open end (``auto_boundary_stations``),
    which stand for a few tens of metres, counted as much as one standing for 250: on drawn
    net 502 their entering and leaving vehicles put the speed 0.49 m/s above the
    trajectories' mean (18.30 against 17.81 m/s; so weighted, 17.89). Density per lane: E2 vehicles per metre over the lane-metres they cover
    (``e2_covered_density``), E1 flow / speed averaged over the detectors. Vehicles on the section: E1 stations' density summed over their lanes and
    integrated along the arc (each station stands for the stretch half-way to its
    neighbours: lane counts that change along the section are weighted right); E2: their
    vehicles scaled to the section's lane length. Spacing spread and speed bounds: from
    the per-vehicle passages.
    """
    spacings = passage_spacings(passages)
    det = det.assign(k_point_vpkm=loop_densities(det, passages))
    stations = np.sort(det.loc[det["kind"] == "e1", "arc_m"].unique())
    cells = (
        dict(zip(stations, station_cells(stations, section), strict=True)) if len(stations) else {}
    )
    rows = []
    det = det[det["begin_s"] >= warmup_s - 1e-9]
    for (run, begin, end), g in det.groupby(["run", "begin_s", "end_s"], sort=True):
        e1, e2 = g[g["kind"] == "e1"], g[g["kind"] == "e2"]
        if len(e2):
            ss = e2["sampled_seconds_s"].to_numpy()
            v = e2["speed_mps"].to_numpy()
            speed = float(np.nansum(v * ss) / ss.sum()) if ss.sum() > 0 else np.nan
            density = e2_covered_density(e2, section)
            vehicles = vehicles_fs = density / 1000.0 * section.lane_length_m
        else:
            n, v = e1["n_veh"].to_numpy(), e1["speed_mps"].to_numpy()
            ok = n > 0
            # Each passage weighs the arc its station stands for: sum q L / sum (q L / v).
            w = n * e1["arc_m"].map(cells).to_numpy(dtype=float)
            speed = float(w[ok].sum() / (w[ok] / v[ok]).sum()) if ok.any() else np.nan
            density = float(e1["k_point_vpkm"].mean())
            vehicles = integrate_stations(station_density(e1, section), section)
            # The former estimate, kept for comparison: flow / speed only, each station's
            # lanes summed and held constant over its cell.
            per_station = e1.groupby("arc_m")["density_vpkm"].sum()
            vehicles_fs = float(sum(k / 1000.0 * cells[a] for a, k in per_station.items()))
        ip = passages[
            (passages["run"] == run) & (passages["time_s"] >= begin) & (passages["time_s"] < end)
        ]
        sp = spacings[
            (spacings["run"] == run) & (spacings["time_s"] >= begin) & (spacings["time_s"] < end)
        ]
        ps = ip["speed_mps"].to_numpy()
        d = sp["spacing_m"].to_numpy()
        d = d[d >= min_spacing_m * 0.5]  # a lane change between two loops is not a spacing
        rows.append(
            {
                "run": run,
                "begin_s": begin,
                "end_s": end,
                "source": "detectors",
                "mean_speed_mps": speed,
                "std_speed_mps": float(ps.std(ddof=1)) if ps.size > 1 else np.nan,
                "density_vpkm_lane": density,
                "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                "std_spacing_m": float(d.std(ddof=1)) if d.size > 1 else np.nan,  # sample std
                "speed_min_mps": float(ps.min()) if ps.size else np.nan,
                "speed_max_mps": float(ps.max()) if ps.size else np.nan,
                "vehicles": vehicles,
                "vehicles_flow_speed": vehicles_fs,
            }
        )
    return pd.DataFrame(rows)


def trajectory_macro(
    traj: pd.DataFrame, section: Section, interval_s: float, warmup_s: float, end_s: float
) -> pd.DataFrame:
    """The same statistics from the full trajectories (what the simulation knows)."""
    rows = []
    bounds = np.arange(warmup_s, end_s + 1e-9, interval_s)
    for run, g in traj.groupby("run", sort=True):
        for begin, end in zip(bounds[:-1], bounds[1:], strict=True):
            w = g[(g["time_s"] >= begin) & (g["time_s"] < end)]
            if w.empty:
                continue
            spacing = []
            for _, s in w.groupby("time_s"):
                # Along the lane connections, as the environment finds leaders (lane
                # indices shift where a lane is added or dropped); lane ends are no spacing.
                lead, sp = section_leaders(
                    section, s["lane_index"].to_numpy(), s["arc_m"].to_numpy()
                )
                spacing.append(sp[lead >= 0])
            d = np.concatenate(spacing) if spacing else np.array([])
            n_t = w.groupby("time_s").size().mean()
            density = n_t / section.lane_length_m * 1000.0
            rows.append(
                {
                    "run": run,
                    "begin_s": begin,
                    "end_s": end,
                    "source": "trajectories",
                    "mean_speed_mps": float(w["speed_mps"].mean()),
                    "std_speed_mps": float(w["speed_mps"].std(ddof=0)),
                    "density_vpkm_lane": density,
                    "mean_spacing_m": 1000.0 / density if density > 0 else np.nan,
                    "std_spacing_m": float(d.std()) if d.size > 1 else np.nan,
                    "speed_min_mps": float(w["speed_mps"].min()),
                    "speed_max_mps": float(w["speed_mps"].max()),
                    "vehicles": float(n_t),
                }
            )
    return pd.DataFrame(rows)


K_ESTIMATE_COLUMNS = ("run", "time_s", "n_vehicles", "n_observed", "k_true", "k_est", "k_error")


def k_summary(k_df: pd.DataFrame, section: Section) -> dict[str, float]:
    """The K estimate's error: mean, mean absolute, and mean absolute per lane."""
    if k_df.empty:
        return {"snapshots": 0}
    err = k_df["k_error"].to_numpy(dtype=float)
    lanes = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    return {
        "snapshots": len(err),
        "mean_error_veh": float(err.mean()),
        "mean_abs_error_veh": float(np.abs(err).mean()),
        "mean_abs_error_per_lane_veh": float(np.abs(err).mean() / lanes),
        "mean_k_true": float(k_df["k_true"].mean()),
    }
