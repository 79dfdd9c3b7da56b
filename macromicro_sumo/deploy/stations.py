"""Stations of the comparison (``deploy.compare``): the loops of ``detectors.csv`` grouped
into cross-sections, and their flow, speed and density per run and interval."""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.deploy.intervals import interval_length_s

# Loops of one kind less than this far apart along the section form one station (a
# user's loops across the lanes of a carriageway are rarely at exactly the same position).
STATION_TOLERANCE_M = 5.0
ALL_LANES = -1  # the ``lane`` of a station's row aggregated over its lanes

KEYS = ["run", "station", "lane", "begin_s", "end_s"]
MEASURES = ("flow_vph", "speed_mps", "density_vpkm")
STATION_COLUMNS = [*KEYS, "arc_m", "n_veh", *MEASURES]


def station_names(kind: pd.Series, arc_m: pd.Series, lane: pd.Series) -> pd.Series:
    """Station of every loop: loops of one kind within ``STATION_TOLERANCE_M`` of the next
    along the arc are one station, named by kind and mean position (``e1_500m``), but a
    loop on a lane the station has already starts the next station: a station is one
    cross-section, and its flow the sum over its lanes (two loops of one lane 4 m apart,
    a boundary loop beside a spacing loop, counted its vehicles twice)."""
    out = pd.Series("", index=arc_m.index, dtype=object)
    taken: set[str] = set()
    for k, idx in arc_m.groupby(kind).groups.items():
        loops = pd.DataFrame({"arc": arc_m[idx], "lane": lane[idx]})
        places = loops.drop_duplicates().sort_values(["arc", "lane"]).to_numpy()
        cluster, lanes, prev = np.zeros(len(places), dtype=int), set(), -np.inf
        for i, (a, ln) in enumerate(places):
            if a - prev > STATION_TOLERANCE_M or ln in lanes:
                cluster[i], lanes = cluster[i - 1] + (i > 0), set()
            else:
                cluster[i] = cluster[i - 1]
            lanes.add(ln)
            prev = a
        centre = pd.Series(places[:, 0]).groupby(cluster).transform("mean").to_numpy()
        names = {}
        for c in np.unique(cluster):
            name = f"{str(k).lower()}_{centre[cluster == c][0]:.0f}m"
            n = 2
            while name in taken:  # two stations whose positions round alike
                name = f"{str(k).lower()}_{centre[cluster == c][0]:.0f}m_{n}"
                n += 1
            taken.add(name)
            names[c] = name
        of = {(a, ln): names[c] for (a, ln), c in zip(map(tuple, places), cluster, strict=True)}
        out[idx] = [of[pair] for pair in zip(loops["arc"], loops["lane"], strict=True)]
    return out


def loop_rows(det: pd.DataFrame) -> pd.DataFrame:
    """One row per detector and interval from ``detectors.csv``: flow and speed as the file
    has them, density ``density_vpkm`` (E1: flow / speed; E2: vehicles on the detector per km).
    """
    out = det.reindex(
        columns=["run", "kind", "lane_index", "arc_m", "begin_s", "end_s", "n_veh", *MEASURES]
    ).copy()
    out["sampled_s"] = det.get("sampled_seconds_s", pd.Series(np.nan, index=det.index))
    out.insert(1, "station", station_names(det["kind"], det["arc_m"], det["lane_index"]))
    return out


def station_table(det: pd.DataFrame) -> pd.DataFrame:
    """Per run, station and interval: the station over all its lanes (``lane == ALL_LANES``)
    and, at stations with loops on more than one lane, every lane on its own. Intervals
    shorter than the detectors' period (the partial one SUMO writes at the end) are left out.

    Over the lanes: flow and density add up (veh/h and veh/km of the cross-section); speed
    is the space-mean speed of the vehicles that passed (harmonic mean of the lanes'
    speeds weighted by their counts) for loops, the mean weighted by time on the detector
    for lane-area detectors.
    """
    loops = loop_rows(det)
    loops[["begin_s", "end_s"]] = loops[["begin_s", "end_s"]].round(3)
    # SUMO closes a run with a partial interval (120 s to 120.5 s): not a measurement.
    length = loops["end_s"] - loops["begin_s"]
    loops = loops[length >= interval_length_s(loops) - 1e-6]
    v, n = loops["speed_mps"].to_numpy(float), loops["n_veh"].to_numpy(float)
    passed = np.isfinite(v) & (v > 0) & (n > 0)
    ss = loops["sampled_s"].fillna(0.0).to_numpy(float)
    timed = np.isfinite(v) & (ss > 0)
    loops = loops.assign(
        w_n=np.where(passed, n, 0.0),
        w_inv=np.where(passed, n / np.where(passed, v, 1.0), 0.0),
        w_ss=np.where(timed, ss, 0.0),
        w_ssv=np.where(timed, ss * np.where(timed, v, 0.0), 0.0),
    )
    group = loops.groupby(["run", "station", "begin_s", "end_s"], sort=True)
    agg = group.agg(
        arc_m=("arc_m", "mean"),
        lanes=("lane_index", "size"),
        kind=("kind", "first"),
        loop_speed=("speed_mps", "first"),
        n_veh=("n_veh", "sum"),
        flow_vph=("flow_vph", lambda x: x.sum(min_count=1)),
        density_vpkm=("density_vpkm", lambda x: x.sum(min_count=1)),
        w_n=("w_n", "sum"),
        w_inv=("w_inv", "sum"),
        w_ss=("w_ss", "sum"),
        w_ssv=("w_ssv", "sum"),
    ).reset_index()
    with np.errstate(divide="ignore", invalid="ignore"):
        harmonic = np.where(agg["w_inv"] > 0, agg["w_n"] / agg["w_inv"], np.nan)
        timed_mean = np.where(agg["w_ss"] > 0, agg["w_ssv"] / agg["w_ss"], np.nan)
    speed = np.where(agg["kind"] == "e2", timed_mean, harmonic)
    # A one-loop station is its loop: its speed as written, not re-derived through n / v.
    agg["speed_mps"] = np.where(agg["lanes"] == 1, agg["loop_speed"], speed)
    agg["lane"] = ALL_LANES
    multi = loops.groupby(["run", "station"])["lane_index"].transform("nunique") > 1
    lanes = loops[multi].rename(columns={"lane_index": "lane"})
    out = pd.concat([agg[STATION_COLUMNS], lanes[STATION_COLUMNS]], ignore_index=True)
    return out.sort_values(KEYS, kind="stable").reset_index(drop=True)
