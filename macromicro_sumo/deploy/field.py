"""What a deployment on field data (``[data] source = "files"``) is made of: loops where the
field stations are, and a demand.

A files-sourced ground truth has no simulated runs to re-run, so a deployment builds each
held-out recording's SUMO run from what a user with field data has:

* **detectors**: an induction loop on every lane of every station, at the station's arc,
  named as the station's lane in ``detectors.csv`` and aggregated over the stations'
  interval, so that ``deploy.compare`` matches them station by station, lane by lane and
  interval by interval (and ``deploy.calibrate`` detector by detector);
* **demand**: the scenario's own route files when it has any (the network's real routes
  and vTypes); else one demand per recording from its station counts, sampled by SUMO's
  routeSampler (``sumo.route_sampler``): every way on and off the section as candidates,
  the vehicles entering each station's edge over the compared window as counts (the mean
  over the edge's stations of their summed lanes), held at that rate from t = 0 so the road
  is full when the comparison starts; departures uniform in time (the recording's waves
  within it are not reproduced); vTypes: the files' vtypes with their lengths (SUMO's
  defaults otherwise), drawn in the files' proportions.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import DetectorSpec
from macromicro_sumo.sumo.route_sampler import (
    candidate_routes,
    edge_counts_xml,
    routes_xml,
    sample_routes,
)
from macromicro_sumo.truth.section_detectors import Placed

STATION_SOURCE = "station"  # ``source`` of a deployment's loop at a field station
FIELD_TYPE = "field"  # the vTypeDistribution of a sampled demand
DEPARTURE = 'departLane="best" departSpeed="max"'


def check_station_grid(det: pd.DataFrame, interval_s: float, where: str) -> None:
    """SUMO's loops aggregate over [k interval, (k + 1) interval) from t = 0: the stations'
    intervals must lie on that grid to be compared interval by interval."""
    off = np.abs(det["begin_s"] / interval_s - np.round(det["begin_s"] / interval_s))
    if (off > 1e-6).any():
        t = float(det.loc[off > 1e-6, "begin_s"].iloc[0])
        raise UserError(
            f"{where}: a station interval starts at t = {t:g} s, off the {interval_s:g} s grid "
            "a deployment's loops aggregate on (from t = 0); accepted: interval starts at "
            "multiples of the interval (shift data.stations.clock_origin or clock_offset_s)"
        )


def station_loops(det: pd.DataFrame, section: Section, interval_s: float) -> list[Placed]:
    """A loop at every station lane of ``det`` (``detectors.csv`` of a files-sourced truth),
    named by its ``detector_id``, at its arc on the section."""
    lane_ids = section.edge_lane_ids
    placed = []
    rows = det.drop_duplicates("detector_id").sort_values(["arc_m", "lane_index"])
    for r in rows.itertuples(index=False):
        e = int(section.edge_index(np.array([r.arc_m]))[0])
        lanes = {section.lanes[lid][1]: lid for lid in lane_ids[e]}
        lane_id = lanes.get(int(r.lane_index))
        pos = (r.arc_m - section.lanes[lane_id][2]) / section.lanes[lane_id][3] if lane_id else -1
        if lane_id is None or not 0.0 <= pos <= section.lengths_m[e]:
            raise UserError(
                f"detectors.csv: station {r.detector_id} (arc {r.arc_m:g} m, lane "
                f"{r.lane_index}) is not on a lane of an edge of the section (a junction?); "
                "accepted: a station on an edge's lane"
            )
        spec = DetectorSpec(str(r.detector_id), "e1", lane_id, float(pos), 0.0, interval_s, "")
        placed.append(Placed(spec, STATION_SOURCE, int(r.lane_index), float(r.arc_m)))
    return placed


def edge_counts(det: pd.DataFrame, section: Section, from_s: float, to_s: float) -> dict[str, int]:
    """Vehicles entering each section edge that holds a station over [0, ``to_s``): the
    stations' count over [``from_s``, ``to_s``) (summed over a station's lanes, averaged
    over the edge's stations) held at the same rate from t = 0."""
    w = det[(det["begin_s"] >= from_s - 1e-9) & (det["end_s"] <= to_s + 1e-9)]
    if w.empty:
        raise UserError(
            f"detectors.csv: no station interval within [{from_s:g}, {to_s:g}] s to count "
            "a demand from"
        )
    per_station = w.groupby("arc_m")["n_veh"].sum()
    edge = section.edge_ids
    idx = section.edge_index(per_station.index.to_numpy(dtype=float))
    by_edge = per_station.groupby(np.asarray(idx)).mean()
    scale = to_s / max(float(w["end_s"].max() - w["begin_s"].min()), 1e-9)
    return {edge[int(e)]: int(round(n * scale)) for e, n in by_edge.items()}


def field_vtypes_xml(vtypes: pd.DataFrame) -> str:
    """The files' vtypes as SUMO vTypes (their lengths, SUMO's defaults otherwise) in a
    distribution ``FIELD_TYPE`` weighted by how many vehicles each has in the files."""
    weight = vtypes["vehicles"].clip(lower=1).to_numpy(dtype=float)
    rows = [f'<routes>\n    <vTypeDistribution id="{FIELD_TYPE}">']
    for r, p in zip(vtypes.itertuples(index=False), weight / weight.sum(), strict=True):
        rows.append(
            f"        <vType id={quoteattr(str(r.vtype))} vClass={quoteattr(str(r.vclass))} "
            f'length="{float(r.length_m):.3f}" probability="{p:.6f}"/>'
        )
    rows.append("    </vTypeDistribution>\n</routes>")
    return "\n".join(rows) + "\n"


def sampled_demand(
    net_file: Path,
    section: Section,
    det: pd.DataFrame,
    vtypes: pd.DataFrame,
    runs: list[int],
    folder: Path,
    seed: int,
    window_s: tuple[float, float],
) -> tuple[Path, dict[int, Path]]:
    """(the vType file, each run's sampled route file) in ``folder``: routeSampler on the
    run's ``edge_counts`` over ``window_s``, seeded ``seed`` + run."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for run in runs:
        candidates, types, count_file, routes = demand_files(folder, run)
        if run == runs[0]:
            candidates.write_text(routes_xml(candidate_routes(net_file, section.edge_ids)))
            types.write_text(field_vtypes_xml(vtypes))
        counts = edge_counts(det[det["run"] == run], section, *window_s)
        count_file.write_text(edge_counts_xml([(0.0, window_s[1], counts)]))
        attrs = f'type="{FIELD_TYPE}" {DEPARTURE}'
        out[run] = sample_routes(candidates, count_file, routes, seed + run, f"r{run}_", attrs)
    return types, out


def demand_files(folder: Path, run: int) -> tuple[Path, Path, Path, Path]:
    """A sampled demand's files for ``run``: (candidate routes, vTypes, counts, routes)."""
    return (
        folder / "candidate_routes.rou.xml",
        folder / "field_vtypes.rou.xml",
        folder / f"counts_run{run}.xml",
        folder / f"sampled_run{run}.rou.xml",
    )
