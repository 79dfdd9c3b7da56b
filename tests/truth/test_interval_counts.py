"""The hidden count from the stations' interval counts alone (``truth.interval_counts``): a
hand-computed queue between two stations, and a congested merge in real SUMO."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from test_hidden_count import merge_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.truth.files import data_toml, export_field_files
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.interval_counts import (
    interval_passages,
    interval_record,
    queued_weight,
)
from macromicro_sumo.truth.section_macro import detector_macro, k_summary
from macromicro_sumo.truth.stations import StationRecord

NO_PASSAGES = pd.DataFrame(
    {c: [] for c in ("run", "detector_id", "time_s", "speed_mps", "length_m")}
)


def loops(rows: list[tuple[str, int, float, float, int, float, float]]) -> pd.DataFrame:
    """E1 rows from (ID, lane, arc, begin, count, speed, occupancy %), 60 s intervals."""
    det = pd.DataFrame(
        rows,
        columns=[
            "detector_id",
            "lane_index",
            "arc_m",
            "begin_s",
            "n_veh",
            "speed_mps",
            "occupancy_pct",
        ],
    )
    return det.assign(
        run=0,
        kind="e1",
        end_s=det["begin_s"] + 60.0,
        flow_vph=det["n_veh"] * 60.0,
        density_vpkm=np.nan,
        length_m=0.0,
    )


def test_interval_counts_spread_evenly_over_each_interval() -> None:
    # A station of two lanes: 1 + 2 vehicles in [0, 60), 0 + 1 in [60, 120): its
    # cumulative count 0, 3, 4 at the bounds crosses 0.5, 1.5, 2.5 at 10, 30, 50 s and 3.5
    # half-way through the second interval.
    det = loops(
        [
            ("s_0", 0, 100.0, 0.0, 1, 20.0, 1.0),
            ("s_1", 1, 100.0, 0.0, 2, 10.0, 2.0),
            ("s_0", 0, 100.0, 60.0, 0, np.nan, 0.0),
            ("s_1", 1, 100.0, 60.0, 1, 10.0, 1.0),
        ]
    )
    p = interval_passages(det)
    np.testing.assert_allclose(p["time_s"], [10.0, 30.0, 50.0, 90.0])
    assert (p["detector_id"] == "i_s_0").all() and p["vehicle_id"].is_unique
    # The station's harmonic speed: 3 / (1 / 20 + 2 / 10) = 12 m/s, then 10 m/s.
    np.testing.assert_allclose(p["speed_mps"], [12.0, 12.0, 12.0, 10.0])


def test_a_queue_between_stations_is_counted_from_the_interval_counts() -> None:
    """One lane of 300 m, stations A, B, C at 50, 150 and 250 m. In [0, 60) 6 vehicles
    cross each at 20 m/s (5 veh/km). In [60, 120) 6 cross A and B, none C (a queue stands
    over it, occupancy 100 %: 200 veh/km): 6 more between B and C by its end.

    Density alone at 90 s: 5 veh/km on [0, 150], 5 -> 200 on [150, 250], 200 on [250, 300]:
    0.75 + 10.25 + 10 = 21 vehicles. From the counts: A-B holds none more than at the start
    and takes the density's 0.5 for its constant; B-C, B's passages spread at 65, 75, 85 s
    gives 3 at 90 s, plus its constant, the offsets 0.5 (interval 1, weight 1) and 10.25 -
    3 = 7.25 (interval 2, B-C's slower station standing: weight 0.02), (0.5 + 0.145) /
    1.02 = 0.632; the ends keep the density's 0.25 + 10. Sum: 0.5 + 3.632 + 10.25 = 14.38;
    the slowest station stands: the counts' estimate alone. At 30 s, in free flow, the
    density estimate alone: 1.5 vehicles. One vehicle observed each time."""
    section = Section(
        ("a",),
        False,
        np.array([0.0]),
        np.array([300.0]),
        np.array([0.0]),
        np.array([1]),
        np.array([[30.0]]),
        {},
    )
    free = [
        (f"{s}_0", 0, arc, 0.0, 6, 20.0, 2.5)
        for s, arc in zip("ABC", (50.0, 150.0, 250.0), strict=True)
    ]
    queue = [
        ("A_0", 0, 50.0, 60.0, 6, 20.0, 2.5),
        ("B_0", 0, 150.0, 60.0, 6, 20.0, 2.5),
        ("C_0", 0, 250.0, 60.0, 0, np.nan, 100.0),
    ]
    det = loops(free + queue)
    traj = pd.DataFrame({"run": 0, "time_s": [30.0, 90.0], "observed": True, "speed_mps": 0.0})
    macro = detector_macro(det, NO_PASSAGES, 0.0, 6.5, section)
    np.testing.assert_allclose(macro["vehicles"], [1.5, 21.0])
    record = StationRecord(
        det,
        interval_passages(det),
        np.array([]),  # no ramp
        interval_counts=True,
        weight=queued_weight(det),
    )
    np.testing.assert_allclose(record.weight["weight"], [0.0, 1.0])
    before = k_estimates(traj, macro, section, 30.0, 60.0)
    after = k_estimates(traj, macro, section, 30.0, 60.0, record)
    assert before["k_est"].tolist() == [1, 20]  # round(1.5) - 1, 21 - 1
    assert after["k_est"].tolist() == [1, 13]  # round(14.38) - 1


def test_congested_merge_from_interval_counts(tmp_path: Path) -> None:
    """The merge's queue from its lane drop (test_hidden_count), every station's intervals
    alone as field data gives them: within a vehicle per lane, and closer than the density
    estimate alone."""
    toml = merge_scenario(tmp_path, 1300.0, 400.0, 6.0, boundary=True)
    gt = tmp_path / "gt"
    assert main(["simulate", str(toml), "--out", str(gt), "--quiet"]) == 0
    section = Section.read(gt / "section.json")
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    det = pd.read_csv(gt / "detectors.csv")
    macro = detector_macro(det, NO_PASSAGES, 60.0, 7.5, section)
    record = interval_record(det, section, read_net(tmp_path / "m.net.xml"))
    assert record is not None
    before = k_summary(k_estimates(traj, macro, section, 5.0, 30.0), section)
    after = k_summary(k_estimates(traj, macro, section, 5.0, 30.0, record), section)
    assert after["mean_abs_error_per_lane_veh"] <= 1.0, (before, after)  # 0.56 measured
    assert after["mean_abs_error_per_lane_veh"] < before["mean_abs_error_per_lane_veh"]  # 2.60
    # The same through field files (PeMS stations, NGSIM trajectories): the files' K is the
    # interval counts' (within a vehicle; PeMS rounds), not the density estimate's.
    data = export_field_files(gt, tmp_path / "field")
    for kind in ("trajectories", "stations"):
        data[kind]["files"] = [str(tmp_path / "field" / f) for f in data[kind]["files"]]
    files_toml = tmp_path / "files.toml"
    files_toml.write_text(toml.read_text() + "\n" + data_toml(data))
    assert main(["simulate", str(files_toml), "--out", str(tmp_path / "gt_files"), "--quiet"]) == 0
    k = pd.read_csv(tmp_path / "gt_files" / "k_estimate.csv")
    truth = pd.read_csv(gt / "k_estimate.csv")[["run", "time_s", "k_true"]]
    m = k.drop(columns="k_true").merge(truth, on=["run", "time_s"])
    lanes = float((section.n_lanes * section.lengths_m).sum() / section.lengths_m.sum())
    per_lane = float(np.abs(m["k_est"] - m["k_true"]).mean()) / lanes
    assert len(m) > 30 and per_lane <= 1.0, per_lane
