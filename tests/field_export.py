"""Field files the package's exporters do not write, for the readers' tests: a ground-truth
folder's observed vehicles as SUMO FCD, highD tracks and a generic CSV; its E1 loops as SUMO
E1 output (with the additional file placing them) and a generic station CSV. Each returns
what a user would write into the mapping. (NGSIM and PeMS: ``fielddata.export``, which
``data.source = "files"`` tests write.)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.export import e1_rows, observed_rows
from macromicro_sumo.fielddata.mapping import (
    StationMapping,
    StationPlace,
    TrajectoryMapping,
    lane_number,
    lanes_at,
)
from macromicro_sumo.files import write_csv, write_text
from macromicro_sumo.road.section import Section

HIGHD_EXPORT_MAPPING = TrajectoryMapping(lane_numbering="left", first_lane=2, frame_rate_hz=2.0)


def lane_position(section: Section, lane: int, arc_m: float) -> tuple[str, float]:
    """(SUMO lane ID, position on it) of a section position, junctions on their internal
    lane: the exact inverse of ``Section.locate`` (``to_lane`` moves junction positions)."""
    s = float(np.mod(arc_m, section.length_m)) if section.closed else float(arc_m)
    e = int(section.edge_index(np.array([s]))[0])
    on_edge = s <= section.offsets_m[e] + section.lengths_m[e] + 1e-9
    for lane_id, (ei, idx, start, scale) in section.lanes.items():
        if ei == e and idx == lane and lane_id.startswith(":") != on_edge:
            return lane_id, (s - start) / scale
    raise UserError(f"no lane {lane} at arc {arc_m:.2f} m of the section")


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


def export_e1_xml(gt: Path, output: Path, additional: Path, run: int = 0) -> StationMapping:
    """SUMO E1 interval output and the additional file that places its loops."""
    section, det = e1_rows(gt, run)
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


def export_generic_stations(gt: Path, path: Path, run: int = 0) -> StationMapping:
    """One row per loop and interval: station, begin_s, end_s, flow [veh/h], speed [m/s]
    (empty: no vehicle), occupancy [%]; each loop placed at its lane and arc."""
    _, det = e1_rows(gt, run)
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
