"""A ground-truth folder exported into field layouts: NGSIM and PeMS.

No public NGSIM, highD or PeMS sample is reachable from the machines this tool is tested
on, so the field-data path (``truth.files``, ``scripts/export_field_data.py``) runs on files
written here from a real SUMO run (``macromicro simulate``): the observed vehicles'
trajectories as NGSIM (feet, lanes from the left, with Gaussian position noise from a
seeded generator and speeds differenced from the noisy positions, as NGSIM's own were) and
the E1 detectors as PeMS. Each exporter returns what a user would write into the mapping;
the tests' other layouts: ``tests/field_export.py``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.fielddata.mapping import (
    StationMapping,
    StationPlace,
    TrajectoryMapping,
    lane_number,
    lanes_at,
)
from macromicro_sumo.fielddata.stations import PEMS_FIXED, PEMS_LANE, PEMS_MAPPING
from macromicro_sumo.fielddata.trajectories import NGSIM_MAPPING, derive_rates
from macromicro_sumo.files import write_csv
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import FT, SPEED_UNITS

NGSIM_EPOCH_MS = 1_118_846_980_200  # US-101's first Global_Time (2005-06-15 07:49:40.2 PDT)
PEMS_ORIGIN = "2024-01-01T00:00:00"


def _truth(gt: Path, run: int) -> tuple[Section, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(section, all vehicles' rows of ``run``, detectors of ``run``, vtypes) of a folder."""
    section = Section.read(gt / "section.json")
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    det = pd.read_csv(gt / "detectors.csv", dtype={"detector_id": str})
    vt = pd.read_csv(gt / "vtypes.csv", dtype={"vtype": str})
    return section, traj[traj["run"] == run], det[det["run"] == run], vt


def observed_rows(gt: Path, run: int = 0) -> tuple[Section, pd.DataFrame]:
    """The observed vehicles' rows of ``run`` (sorted by vehicle, time), with each row's
    true leader among all vehicles, hidden or not (along the lane connections, as the
    observation finds it: ``section_leaders``), its front-to-front spacing and speed (0 and
    NaN without a vehicle ahead: a lane's end is no vehicle), and the vehicle's length:
    what an instrumented vehicle's radar measures."""
    section, traj, _, vt = _truth(gt, run)
    traj = traj.reset_index(drop=True)
    leader = np.full(len(traj), -1)
    spacing = np.zeros(len(traj))
    for idx in traj.groupby("time_s").indices.values():
        ld, sp = section_leaders(
            section, traj["lane_index"].to_numpy()[idx], traj["arc_m"].to_numpy()[idx]
        )
        leader[idx] = np.where(ld >= 0, idx[np.maximum(ld, 0)], -1)
        spacing[idx] = np.where(ld >= 0, sp, 0.0)
    ids = traj["vehicle_id"].to_numpy()
    traj["leader_id"] = np.where(leader >= 0, ids[np.maximum(leader, 0)], "")
    traj["spacing_m"] = spacing
    speed = traj["speed_mps"].to_numpy()
    traj["leader_speed_mps"] = np.where(leader >= 0, speed[np.maximum(leader, 0)], np.nan)
    traj["length_m"] = traj["vtype"].map(dict(zip(vt["vtype"], vt["length_m"], strict=True)))
    lengths = traj["length_m"].to_numpy()
    traj["leader_length_m"] = np.where(leader >= 0, lengths[np.maximum(leader, 0)], np.nan)
    # Field layouts number every vehicle of a recording, so a hidden leader has a number too.
    number = numeric_ids(traj.sort_values("time_s", kind="stable")["vehicle_id"])
    traj["number"] = traj["vehicle_id"].map(number)
    traj["leader_number"] = traj["leader_id"].map(lambda x: number.get(x, 0) if x else 0)
    obs = traj[traj["observed"]].sort_values(["vehicle_id", "time_s"], kind="stable")
    return section, obs.reset_index(drop=True)


def numeric_ids(ids: pd.Series) -> dict[str, int]:
    """Field layouts number their vehicles: 1, 2, ... in order of first appearance."""
    return {v: i + 1 for i, v in enumerate(pd.unique(ids))}


# --------------------------------------------------------------------------- trajectories


def export_ngsim(
    gt: Path, path: Path, run: int = 0, noise_m: float = 0.3, seed: int = 0
) -> tuple[TrajectoryMapping, dict[str, int]]:
    """NGSIM columns in feet, lanes numbered from the left (1 = leftmost), Global_Time in ms.
    ``Local_Y`` gets N(0, ``noise_m``) noise; ``v_Vel`` and ``v_Acc`` are differenced from
    the noisy positions, so they are as noisy as NGSIM's. Returns the mapping and the ids."""
    section, obs = observed_rows(gt, run)
    rng = np.random.default_rng(seed)
    ids = dict(zip(obs["vehicle_id"], obs["number"], strict=False))
    vid = obs["number"].to_numpy()
    t = obs["time_s"].to_numpy()
    # Noise may not push a position off the section (the recorded stretch): clipped there.
    y = np.clip(
        obs["arc_m"].to_numpy() + rng.normal(0.0, noise_m, len(obs)), 0.0, section.length_m - 0.01
    )
    v = derive_rates(vid, t, y)
    a = derive_rates(vid, t, v)
    dt = float(np.median(np.diff(np.unique(t))))
    lanes = lane_number(obs["lane_index"].to_numpy(), "left", 1, 0, lanes_at(section, obs["arc_m"]))
    frame = np.rint(t / dt).astype(np.int64)
    prec = obs["leader_number"]
    # The radar's range: the true spacing with N(0, noise_m) noise (kept above 0: 0 is
    # NGSIM's "no leader"); 0 where nothing drives ahead.
    has = prec.to_numpy() > 0
    space = np.where(
        has, np.maximum(obs["spacing_m"].to_numpy() + rng.normal(0.0, noise_m, len(obs)), 0.1), 0.0
    )
    df = pd.DataFrame(
        {
            "Vehicle_ID": vid,
            "Frame_ID": frame,
            "Total_Frames": obs.groupby("vehicle_id")["time_s"].transform("size").to_numpy(),
            "Global_Time": NGSIM_EPOCH_MS + np.rint(t * 1000).astype(np.int64),
            "Local_X": (lanes - 0.5) * 12.0,  # lane centres of 12 ft lanes
            "Local_Y": y / FT,
            "Global_X": 0.0,
            "Global_Y": 0.0,
            "v_Length": obs["length_m"].to_numpy() / FT,
            "v_Width": 6.0,
            "v_Class": 2,
            # Differenced from noisy positions, a crawling vehicle's speed dips below 0;
            # NGSIM's own v_Vel never does (and the reader refuses negative speeds).
            "v_Vel": np.maximum(v, 0.0) / FT,
            "v_Acc": a / FT,
            "Lane_ID": lanes,
            "Preceding": prec.to_numpy(),
            "Following": 0,
            "Space_Headway": space / FT,
            "Time_Headway": np.where(
                has & (obs["speed_mps"] > 0.1),
                space / obs["speed_mps"].clip(lower=0.1).to_numpy(),
                np.where(has, 9999.99, 0.0),
            ),
        }
    )
    write_csv(df, path, float_format="%.3f")
    mapping = dataclasses.replace(NGSIM_MAPPING, clock_offset_s=-NGSIM_EPOCH_MS / 1000.0, run=run)
    return mapping, ids


# --------------------------------------------------------------------------- stations


def e1_rows(gt: Path, run: int) -> tuple[Section, pd.DataFrame]:
    """(section, the E1 loops' rows of ``run``) of a ground-truth folder."""
    section, _, det, _ = _truth(gt, run)
    return section, det[det["kind"] == "e1"].reset_index(drop=True)


def export_pems(gt: Path, path: Path, run: int = 0, origin: str = PEMS_ORIGIN) -> StationMapping:
    """PeMS ``station_5min`` columns at the ground truth's interval: one station per arc of
    E1 loops, lanes numbered from the left, flows as vehicles per interval, occupancy as a
    fraction (4 decimals), speeds in mph (1 decimal), 100 % observed; a header row."""
    section, det = e1_rows(gt, run)
    det = det.assign(station=det["arc_m"].map(lambda a: f"{400000 + round(a)}"))
    n_max = int(lanes_at(section, det["arc_m"].to_numpy()).max())
    interval = float((det["end_s"] - det["begin_s"]).median())
    t0 = pd.Timestamp(origin)
    rows = []
    for (b, st), grp in det.groupby(["begin_s", "station"], sort=True):
        here = int(lanes_at(section, grp["arc_m"].to_numpy()[:1])[0])
        lanes = lane_number(grp["lane_index"].to_numpy(), "left", 1, 0, np.full(len(grp), here))
        flow = grp["n_veh"].to_numpy(dtype=float)
        mph = grp["speed_mps"].to_numpy() / SPEED_UNITS["mph"]
        occ = grp["occupancy_pct"].to_numpy() / 100.0
        moving = flow > 0
        total_speed = (mph[moving] * flow[moving]).sum() / flow.sum() if moving.any() else np.nan
        row = {
            "Timestamp": (t0 + pd.Timedelta(seconds=float(b))).strftime("%m/%d/%Y %H:%M:%S"),
            "Station": st,
            "District": 4,
            "Freeway": 101,
            "Direction": "N",
            "Lane Type": "ML",
            "Station Length": 0.155,
            "Samples": int(interval // 30) * len(grp),
            "% Observed": 100,
            "Total Flow": int(flow.sum()),
            "Avg Occupancy": round(float(occ.mean()), 4),
            "Avg Speed": "" if np.isnan(total_speed) else round(float(total_speed), 1),
        }
        for k in range(1, n_max + 1):
            hit = np.flatnonzero(lanes == k)
            j = int(hit[0]) if hit.size else -1
            vals = (
                ["", "", "", "", ""]
                if j < 0
                else [
                    int(interval // 30),
                    int(flow[j]),
                    round(float(occ[j]), 4),
                    "" if np.isnan(mph[j]) else round(float(mph[j]), 1),
                    1,
                ]
            )
            row |= {f"Lane {k} {c}": v for c, v in zip(PEMS_LANE, vals, strict=True)}
        rows.append(row)
    df = pd.DataFrame(rows)
    assert tuple(df.columns[: len(PEMS_FIXED)]) == PEMS_FIXED
    write_csv(df, path, float_format="%.4f")
    places = tuple(
        StationPlace(id=st, arc_m=float(a))
        for st, a in det.groupby("station")["arc_m"].first().items()
    )
    return dataclasses.replace(
        PEMS_MAPPING, stations=places, clock_origin=origin, interval_s=interval, run=run
    )
