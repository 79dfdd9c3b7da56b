"""Readers on small hand-written files: SUMO E2 output, a header-less PeMS file with
unobserved lanes, cleaning flags, the data report, and mappings from scenario tables."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from field_export import lane_position

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata.cleaning import (
    clean_stations,
    clean_trajectories,
    leader_speed_from_gap,
)
from macromicro_sumo.fielddata.mapping import (
    StationMapping,
    lane_index,
    lane_number,
    station_mapping,
    trajectory_mapping,
)
from macromicro_sumo.fielddata.report import data_report, write_data_report
from macromicro_sumo.fielddata.stations import read_pems, read_sumo_detectors
from macromicro_sumo.fielddata.trajectories import read_generic_trajectories
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import CleaningConfig, StationPlace, TrajectoryColumns


def test_lane_numbering_round_trips() -> None:
    here = np.array([3, 3, 2, 4])
    idx = np.array([0, 2, 1, 3])
    for numbering, first in (("left", 1), ("right", 0), ("left", 2)):
        num = lane_number(idx, numbering, first, 0, here)
        assert (lane_index(num, numbering, first, 0, here) == idx).all()
    assert lane_number(np.array([0]), "left", 1, 0, np.array([3]))[0] == 3  # NGSIM: rightmost = 3


def test_e2_output_is_placed_by_its_definition(section: Section, tmp_path: Path) -> None:
    lane_id, pos = lane_position(section, 0, 40.0)
    (tmp_path / "e2.add.xml").write_text(
        f'<additional><laneAreaDetector id="a" lane="{lane_id}" pos="{pos}" length="50" '
        'period="60" file="e2.xml"/></additional>\n'
    )
    (tmp_path / "e2.xml").write_text(
        '<detector><interval begin="0.00" end="60.00" id="a" sampledSeconds="120" nVehEntered="5" '
        'nVehLeft="5" nVehSeen="6" meanSpeed="20.0" meanTimeLoss="0.1" meanOccupancy="12.0" '
        'maxOccupancy="20" meanMaxJamLengthInVehicles="0" meanVehicleNumber="2.0"/></detector>\n'
    )
    st = read_sumo_detectors(tmp_path / "e2.xml", section, tmp_path / "e2.add.xml")
    row = st.frame.iloc[0]
    assert row["kind"] == "e2" and row["arc_m"] == pytest.approx(40.0)
    # 120 vehicle-seconds in 60 s less 12% occupancy: 1.88 vehicles on 50 m (SUMO counts a
    # vehicle while any part of it is on the area; the occupancy is that excess)
    assert row["density_vpkm"] == pytest.approx(37.6) and np.isnan(row["flow_vph"])


def test_headerless_pems_with_unobserved_lane(section: Section, tmp_path: Path) -> None:
    arc = float(section.offsets_m[2] + 10.0)  # the 3-lane edge of the corridor
    assert section.n_lanes[2] == 3
    lanes = [
        "10,15,0.05,62.0,1",
        "12,20,0.06,60.5,1",
        "0,,,,0",  # lane 3 (rightmost) not observed in this interval
    ]
    rows = [
        f"01/01/2024 00:0{k}:00,400001,4,101,N,ML,0.1,20,66.7,35,0.055,61.2," + ",".join(lanes)
        for k in (0, 5)
    ]
    (tmp_path / "d04.txt").write_text("\n".join(rows) + "\n")
    m = StationMapping(
        stations=(StationPlace(id="400001", arc_m=arc),), lane_numbering="left", first_lane=1
    )
    st = read_pems(tmp_path / "d04.txt", section, m)
    assert sorted(st.frame["lane_index"].unique()) == [1, 2]  # lane 3 has no value at all
    assert st.frame["end_s"].sub(st.frame["begin_s"]).eq(300.0).all()
    assert st.frame.loc[st.frame["lane_index"] == 2, "flow_vph"].iloc[0] == pytest.approx(15 * 12)
    clean = clean_stations(st, CleaningConfig(min_samples=11))
    assert len(clean.frame) == 2 and len(clean.dropped) == 2


def test_cleaning_flags_gaps_outliers_and_jumps(section: Section, tmp_path: Path) -> None:
    t = np.arange(0.0, 20.0, 0.5)
    t = np.concatenate([t[:20], t[26:]])  # 3 s missing: a gap
    v = np.full(len(t), 20.0)
    v[30] = 40.0  # a jump no car makes in 0.5 s
    x = 100.0 + np.cumsum(v) * 0.5
    pd.DataFrame(
        {"vehicle_id": "a", "time_s": t, "position_m": x, "lane": 0, "speed_mps": v}
    ).to_csv(tmp_path / "t.csv", index=False)
    traj = read_generic_trajectories(
        tmp_path / "t.csv", section, columns=TrajectoryColumns(accel="")
    )
    clean = clean_trajectories(traj, CleaningConfig(smoother="ema"))
    assert clean.flags["after_gap"].sum() == 1 and clean.flags["after_gap"].iloc[20]
    assert clean.flags["speed_jump"].sum() == 2  # up and back down
    assert clean.flags["accel_outlier"].any()
    paths = write_data_report(tmp_path / "rep", [clean], [])
    assert all(p.is_file() for p in paths)
    table = pd.read_csv(tmp_path / "rep" / "data_report.csv")
    assert table.loc[0, "gaps"] == 1 and table.loc[0, "speed_jumps"] == 2


def test_mappings_from_scenario_tables() -> None:
    m = trajectory_mapping({"offset_m": 12.5, "direction": -1}, "s.toml", lane_numbering="left")
    assert m.offset_m == 12.5 and m.direction == -1 and m.lane_numbering == "left"
    with pytest.raises(
        UserError, match=r"s.toml: data.trajectories.direction = 0; accepted: 1, -1"
    ):
        trajectory_mapping({"direction": 0}, "s.toml")
    with pytest.raises(UserError, match="speed_unit = 'knots' is not accepted"):
        trajectory_mapping({"speed_unit": "knots"}, "s.toml")
    st = station_mapping(
        {"stations": [{"id": "7", "arc_m": 50.0, "lane": 1}], "interval_s": 300.0}, "s.toml"
    )
    assert st.place("7") == StationPlace(id="7", arc_m=50.0, lane=1) and st.interval_s == 300.0
    with pytest.raises(UserError, match=r"data.stations.stations\[0\].lane = 99"):
        station_mapping({"stations": [{"id": "7", "arc_m": 5.0, "lane": 99}]}, "s.toml")


def test_leader_speed_from_the_smoothed_gap() -> None:
    """Own speed + d gap / dt: a leader at constant speed behind a braking follower comes
    back within the smoothing's end effects; a change of leader (a spacing jump) starts a
    new run and is no speed; rows without a leader stay NaN."""
    t = np.arange(0.0, 40.0, 0.1)
    v = 25.0 - 0.5 * t  # braking follower
    x = 25.0 * t - 0.25 * t**2
    lead_x = 60.0 + 22.0 * t  # leader at 22 m/s
    spacing = lead_x - x
    leader = np.full(len(t), "7", dtype=object)
    spacing[150:] -= 30.0  # a cut-in at t = 15 s: a new leader 30 m nearer, also 22 m/s
    leader[150:] = "9"
    spacing[250:260] = np.nan  # nothing measured ahead
    leader[250:260] = ""
    got = leader_speed_from_gap(t, v, leader, spacing, 0.5, 0.5)
    ok = np.isfinite(got)
    assert (ok == np.isfinite(spacing)).all()
    # Away from the runs' ends (the windows shrink there: 3 widths, twice smoothed).
    ends = np.array([0.0, 15.0, 25.0, 26.0, 39.9])
    inner = ok & (np.abs(t[:, None] - ends).min(axis=1) > 3.0)
    assert np.abs(got[inner] - 22.0).max() < 0.05
    assert np.abs(got[ok] - 22.0).max() < 1.0  # no jump of 30 m read as a speed


def test_generic_gap_and_delta_v_and_no_leader(section: Section, tmp_path: Path) -> None:
    """A generic CSV's bumper gap becomes a spacing with the leader's length from the file
    (a leader not in the file: the file's median length); delta_v = own - leader speed;
    leader 0 / an empty gap is no leader. A file without leader columns: a warning line."""
    arc0 = float(section.offsets_m[0] + 20.0)
    rows = []
    for k in range(6):
        t = 0.5 * k
        rows.append(["a", t, arc0 + 20.0 * t, 0, 20.0, 0.0, 4.0, "b", 30.0, 2.0])
        rows.append(["b", t, arc0 + 34.0 + 18.0 * t, 0, 18.0, 0.0, 6.0, "x", 12.0, -1.0])
        rows.append(["c", t, arc0 - 15.0 + 20.0 * t, 0, 20.0, 0.0, 5.0, "0", "", ""])
    cols = ["id", "t", "pos", "lane", "v", "a", "len", "lead", "gap", "dv"]
    pd.DataFrame(rows, columns=cols).to_csv(tmp_path / "g.csv", index=False)
    columns = TrajectoryColumns(
        vehicle_id="id", time="t", position="pos", lane="lane", speed="v", accel="a",
        length="len", leader_id="lead", gap="gap", delta_v="dv",
    )  # fmt: skip
    got = read_generic_trajectories(tmp_path / "g.csv", section, columns=columns)
    assert got.leader_measured
    f = got.frame.set_index("vehicle_id")
    a, b, c = f.loc["a"].iloc[0], f.loc["b"].iloc[0], f.loc["c"].iloc[0]
    assert a["leader_spacing_m"] == pytest.approx(30.0 + 6.0)  # b's length
    assert a["leader_speed_mps"] == pytest.approx(18.0)
    assert b["leader_spacing_m"] == pytest.approx(12.0 + 5.0)  # x: the median length
    assert b["leader_speed_mps"] == pytest.approx(19.0)
    assert c["leader_id"] == "" and np.isnan(c["leader_spacing_m"])
    # The same file without leader columns: today's pairs, and the report says so.
    bare = read_generic_trajectories(
        tmp_path / "g.csv", section, columns=dataclasses.replace(columns, gap="", delta_v="")
    )
    assert not bare.leader_measured and "leader_spacing_m" not in bare.frame
    text, _ = data_report([clean_trajectories(bare)], [])
    warn = [ln for ln in text.splitlines() if "Warning" in ln]
    assert len(warn) == 1 and "g.csv" in warn[0] and "18 rows" in warn[0]
    text, _ = data_report([clean_trajectories(got)], [])
    assert "Warning" not in text and "12 with a vehicle ahead" in text
