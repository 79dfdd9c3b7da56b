"""Loop detectors on the ring: the additional file that defines them and its parsed output.

Per edge: an E1 induction loop and an instantaneous loop at the same point (per-vehicle
passages, for headways and speed bounds), and an E2 lane-area detector over the whole
lane (space-mean speed and occupancy time). All write to files beside the definition.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.ring import RingGeometry
from macromicro_sumo.scenario.ring import DetectorConfig

E1_FILE, E2_FILE, INSTANT_FILE = "e1.xml", "e2.xml", "instant.xml"

DETECTOR_COLUMNS = [
    "run",
    "detector_id",
    "kind",
    "edge_id",
    "begin_s",
    "end_s",
    "n_veh",
    "flow_vehph",
    "occupancy_pct",
    "speed_mps",
    "harmonic_mean_speed_mps",
    "mean_length_m",
    "sampled_seconds_s",
    "mean_vehicle_number",
    "detector_length_m",
]


def detectors_xml(geo: RingGeometry, cfg: DetectorConfig) -> str:
    rows = []
    period = f"{cfg.interval_s:g}"
    for edge, lane, length in zip(geo.edge_ids, geo.lane_ids, geo.lengths_m, strict=True):
        pos = f"{cfg.e1_position * length:.6f}"
        rows.append(
            f'    <inductionLoop id="e1_{edge}" lane="{lane}" pos="{pos}" period="{period}" file="{E1_FILE}"/>'
        )
        rows.append(
            f'    <instantInductionLoop id="i1_{edge}" lane="{lane}" pos="{pos}" file="{INSTANT_FILE}"/>'
        )
        rows.append(
            f'    <laneAreaDetector id="e2_{edge}" lane="{lane}" pos="0" endPos="{length:.6f}" '
            f'period="{period}" file="{E2_FILE}"/>'
        )
    return "<additional>\n" + "\n".join(rows) + "\n</additional>\n"


def records(path: Path, tag: str, required: bool = True) -> list[dict[str, str]]:
    """Attributes of every ``tag`` element of a SUMO output file (none if it is missing and
    not ``required``: SUMO writes no file for a detector kind that is not defined)."""
    if not path.is_file():
        if not required:
            return []
        raise UserError(f"{path}: detector output missing")
    try:
        return [el.attrib for el in ET.parse(path).getroot().iter(tag)]
    except ET.ParseError as exc:
        raise UserError(f"{path}: detector output is not valid XML ({exc})") from None


def read_run(run_dir: Path, run: int, geo: RingGeometry) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-interval detector table, per-vehicle passages) of one run's SUMO output."""
    lengths = dict(zip(geo.edge_ids, geo.lengths_m.tolist(), strict=True))
    rows = []
    for r in records(run_dir / E1_FILE, "interval"):
        rows.append(
            {
                "run": run,
                "detector_id": r["id"],
                "kind": "E1",
                "edge_id": r["id"].removeprefix("e1_"),
                "begin_s": float(r["begin"]),
                "end_s": float(r["end"]),
                "n_veh": int(r["nVehContrib"]),
                "flow_vehph": float(r["flow"]),
                "occupancy_pct": float(r["occupancy"]),
                "speed_mps": speed_or_nan(r["speed"]),
                "harmonic_mean_speed_mps": speed_or_nan(r["harmonicMeanSpeed"]),
                "mean_length_m": speed_or_nan(r["length"]),
            }
        )
    for r in records(run_dir / E2_FILE, "interval"):
        rows.append(
            {
                "run": run,
                "detector_id": r["id"],
                "kind": "E2",
                "edge_id": r["id"].removeprefix("e2_"),
                "begin_s": float(r["begin"]),
                "end_s": float(r["end"]),
                "n_veh": int(r["nVehSeen"]),
                "occupancy_pct": float(r["meanOccupancy"]),
                "speed_mps": speed_or_nan(r["meanSpeed"]),
                "sampled_seconds_s": float(r["sampledSeconds"]),
                "mean_vehicle_number": float(r["meanVehicleNumber"]),
                "detector_length_m": lengths[r["id"].removeprefix("e2_")],
            }
        )
    det = pd.DataFrame(rows).reindex(columns=DETECTOR_COLUMNS)
    passages = read_passages(run_dir / INSTANT_FILE, run)
    return det, passages


def read_passages(path: Path, run: int, required: bool = True) -> pd.DataFrame:
    """Per-vehicle passages ('enter') of the instantaneous loops in ``path``."""
    return pd.DataFrame(
        [
            {
                "run": run,
                "detector_id": r["id"],
                "time_s": float(r["time"]),
                "vehicle_id": r["vehID"],
                "speed_mps": float(r["speed"]),
                "length_m": float(r["length"]),
            }
            for r in records(path, "instantOut", required)
            if r.get("state") == "enter"
        ],
        columns=["run", "detector_id", "time_s", "vehicle_id", "speed_mps", "length_m"],
    )


def speed_or_nan(value: str | None) -> float:
    """SUMO writes -1 for 'no vehicle in this interval'."""
    v = float(value) if value is not None else -1.0
    return np.nan if v < 0 else v
