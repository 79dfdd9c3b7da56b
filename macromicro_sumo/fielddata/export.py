"""Fixtures written by the project: a ground-truth folder exported into each field layout.

No public NGSIM, highD or PeMS sample is reachable from the machines this tool is tested
on, so the readers are tested on files written here from a real SUMO run (``macromicro
simulate``): the observed vehicles' trajectories as SUMO FCD, NGSIM (feet, lanes from the
left, with Gaussian position noise from a seeded generator and speeds differenced from
the noisy positions, as NGSIM's own were), highD tracks and a generic CSV; the E1
detectors as SUMO E1 output (with the additional file that places them), PeMS and a
generic CSV. Each exporter returns what a user would write into the mapping.
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
    lane_position,
    lanes_at,
)
from macromicro_sumo.fielddata.stations import PEMS_FIXED, PEMS_LANE, PEMS_MAPPING
from macromicro_sumo.fielddata.trajectories import NGSIM_MAPPING, derive_rates
from macromicro_sumo.files import write_csv, write_text
from macromicro_sumo.road.section import Section, section_leaders
from macromicro_sumo.scenario.data import FT, SPEED_UNITS

NGSIM_EPOCH_MS = 1_118_846_980_200  # US-101's first Global_Time (2005-06-15 07:49:40.2 PDT)
PEMS_ORIGIN = "2024-01-01T00:00:00"
HIGHD_EXPORT_MAPPING = TrajectoryMapping(lane_numbering="left", first_lane=2, frame_rate_hz=2.0)


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


def export_fcd(gt: Path, path: Path, run: int = 0) -> TrajectoryMapping:
    """SUMO FCD XML of the observed vehicles (lane IDs, lane positions, speed, acceleration)."""
    section, obs = observed_rows(gt, run)
    obs = obs.sort_values(["time_s", "vehicle_id"], kind="stable")
    out = ['<?xml version="1.0" encoding="UTF-8"?>', "<fcd-export>"]
    for t, grp in obs.groupby("time_s", sort=True):
        out.append(f'    <timestep time="{t:.2f}">')
        for r in grp.itertuples():
            lane_id, pos = lane_position(section, int(r.lane_index), float(r.arc_m))
            out.append(
                f'        <vehicle id="{r.vehicle_id}" type="{r.vtype}" lane="{lane_id}" '
                f'pos="{pos:.4f}" speed="{r.speed_mps:.4f}" acceleration="{r.accel_mps2:.4f}"/>'
            )
        out.append("    </timestep>")
    out.append("</fcd-export>")
    write_text("\n".join(out) + "\n", path)
    return TrajectoryMapping(run=run)


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


def export_highd(gt: Path, path: Path, run: int = 0) -> tuple[TrajectoryMapping, dict[str, int]]:
    """highD ``tracks.csv``: driving towards growing x (direction +1), ``x`` the box's rear,
    ``width`` the vehicle length, lanes numbered from the left starting at 2, one frame per
    simulation step (the mapping's ``frame_rate_hz``)."""
    section, obs = observed_rows(gt, run)
    ids = dict(zip(obs["vehicle_id"], obs["number"], strict=False))
    t = obs["time_s"].to_numpy()
    rate = 1.0 / float(np.median(np.diff(np.unique(t))))
    m = dataclasses.replace(HIGHD_EXPORT_MAPPING, frame_rate_hz=rate, run=run)
    length = obs["length_m"].to_numpy()
    df = pd.DataFrame(
        {
            "frame": np.rint(t * rate).astype(np.int64),
            "id": obs["number"].to_numpy(),
            "x": obs["arc_m"].to_numpy() - length,
            "y": 0.0,
            "width": length,
            "height": 1.8,
            "xVelocity": obs["speed_mps"].to_numpy(),
            "yVelocity": 0.0,
            "xAcceleration": obs["accel_mps2"].to_numpy(),
            "yAcceleration": 0.0,
            # highD's dhw is bumper to bumper; 0 and precedingId 0: nothing ahead.
            "dhw": np.nan_to_num(obs["spacing_m"].to_numpy() - obs["leader_length_m"].to_numpy()),
            "precedingXVelocity": np.nan_to_num(obs["leader_speed_mps"].to_numpy()),
            "precedingId": obs["leader_number"].to_numpy(),
            "laneId": lane_number(
                obs["lane_index"].to_numpy(), "left", 2, 0, lanes_at(section, obs["arc_m"])
            ),
        }
    )
    write_csv(df, path, float_format="%.4f")
    return m, ids


def export_generic_trajectories(gt: Path, path: Path, run: int = 0) -> TrajectoryMapping:
    """The generic CSV's default columns: vehicle_id, time_s, position_m, lane (from the
    right, 0 first), speed_mps, accel_mps2."""
    _, obs = observed_rows(gt, run)
    df = pd.DataFrame(
        {
            "vehicle_id": obs["vehicle_id"],
            "time_s": obs["time_s"],
            "position_m": obs["arc_m"],
            "lane": obs["lane_index"],
            "speed_mps": obs["speed_mps"],
            "accel_mps2": obs["accel_mps2"],
            # The measured leader (read when the column map names them): "", 0, empty.
            "leader_id": obs["leader_id"],
            "spacing_m": obs["spacing_m"],
            "leader_speed_mps": obs["leader_speed_mps"],
        }
    )
    write_csv(df, path, float_format="%.4f")
    return TrajectoryMapping(run=run)


# --------------------------------------------------------------------------- stations


def _e1(gt: Path, run: int) -> tuple[Section, pd.DataFrame]:
    section, _, det, _ = _truth(gt, run)
    return section, det[det["kind"] == "e1"].reset_index(drop=True)


def export_e1_xml(gt: Path, output: Path, additional: Path, run: int = 0) -> StationMapping:
    """SUMO E1 interval output and the additional file that places its loops."""
    section, det = _e1(gt, run)
    defs = ["<additional>"]
    for did, grp in det.groupby("detector_id", sort=True):
        lane_id, pos = lane_position(
            section, int(grp["lane_index"].iloc[0]), float(grp["arc_m"].iloc[0])
        )
        defs.append(
            f'    <inductionLoop id="{did}" lane="{lane_id}" pos="{pos:.4f}" period="60" '
            'file="e1.xml"/>'
        )
    defs.append("</additional>")
    out = ['<?xml version="1.0" encoding="UTF-8"?>', "<detector>"]
    for r in det.sort_values(["begin_s", "detector_id"], kind="stable").itertuples():
        hms = -1.0 if np.isnan(r.speed_mps) else r.speed_mps
        out.append(
            f'    <interval begin="{r.begin_s:.2f}" end="{r.end_s:.2f}" id="{r.detector_id}" '
            f'nVehContrib="{int(r.n_veh)}" flow="{r.flow_vph:.2f}" occupancy="{r.occupancy_pct:.2f}" '
            f'speed="{hms:.2f}" harmonicMeanSpeed="{hms:.2f}" length="5.00" '
            f'nVehEntered="{int(r.n_veh)}"/>'
        )
    out.append("</detector>")
    write_text("\n".join(defs) + "\n", additional)
    write_text("\n".join(out) + "\n", output)
    return StationMapping(run=run)


def export_pems(gt: Path, path: Path, run: int = 0, origin: str = PEMS_ORIGIN) -> StationMapping:
    """PeMS ``station_5min`` columns at the ground truth's interval: one station per arc of
    E1 loops, lanes numbered from the left, flows as vehicles per interval, occupancy as a
    fraction (4 decimals), speeds in mph (1 decimal), 100 % observed; a header row."""
    section, det = _e1(gt, run)
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


def export_generic_stations(gt: Path, path: Path, run: int = 0) -> StationMapping:
    """One row per loop and interval: station, begin_s, end_s, flow [veh/h], speed [m/s]
    (empty: no vehicle), occupancy [%]; each loop placed at its lane and arc."""
    _, det = _e1(gt, run)
    df = pd.DataFrame(
        {
            "station": det["detector_id"],
            "begin_s": det["begin_s"],
            "end_s": det["end_s"],
            "flow": det["flow_vph"],
            "speed": det["speed_mps"],
            "occupancy": det["occupancy_pct"],
        }
    )
    write_csv(df, path, float_format="%.4f")
    places = tuple(
        StationPlace(id=str(d), arc_m=float(g["arc_m"].iloc[0]), lane=int(g["lane_index"].iloc[0]))
        for d, g in det.groupby("detector_id", sort=True)
    )
    return StationMapping(stations=places, run=run)
