"""Bad field files: one line naming the file, the row and the column, and what is accepted."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import field_export
import pandas as pd
import pytest

from macromicro_sumo.errors import UserError
from macromicro_sumo.fielddata import export
from macromicro_sumo.fielddata.stations import read_generic_stations, read_pems
from macromicro_sumo.fielddata.trajectories import (
    read_fcd,
    read_generic_trajectories,
    read_highd,
    read_ngsim,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import StationColumns, StationPlace


def _one_line(exc: pytest.ExceptionInfo, path: Path, *parts: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    for p in parts:
        assert re.search(p, msg), (p, msg)
    return msg


def test_missing_column(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m, _ = export.export_ngsim(field_truth, tmp_path / "n.csv")
    pd.read_csv(tmp_path / "n.csv").drop(columns="Lane_ID").to_csv(tmp_path / "n.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_ngsim(tmp_path / "n.csv", section, m)
    _one_line(exc, tmp_path / "n.csv", "column 'Lane_ID'", "missing")


def test_speeds_in_ft_per_s_declared_as_m_per_s(
    field_truth: Path, section: Section, tmp_path: Path
) -> None:
    m = field_export.export_generic_trajectories(field_truth, tmp_path / "t.csv")
    df = pd.read_csv(tmp_path / "t.csv")
    df["speed_mps"] = df["speed_mps"] / 0.3048 * 1.5  # a fast ft/s file read as m/s
    df.to_csv(tmp_path / "t.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_generic_trajectories(tmp_path / "t.csv", section, m)
    _one_line(
        exc, tmp_path / "t.csv", r"row \d+ \(line \d+\), column 'speed_mps'", r"\[0, 100\]", "ft/s"
    )


def test_trajectory_off_the_section(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m, _ = field_export.export_highd(field_truth, tmp_path / "tracks.csv")
    far = dataclasses.replace(m, offset_m=section.length_m)
    with pytest.raises(UserError) as exc:
        read_highd(tmp_path / "tracks.csv", section, far)
    _one_line(
        exc, tmp_path / "tracks.csv", r"row 1 \(line 2\), column 'x'", "off the section", "offset_m"
    )
    dropped = read_highd(
        tmp_path / "tracks.csv", section, dataclasses.replace(m, offset_m=100.0), outside="drop"
    )
    assert dropped.dropped_off_section > 0


def test_fcd_lane_off_the_section(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m = field_export.export_fcd(field_truth, tmp_path / "fcd.xml")
    text = (tmp_path / "fcd.xml").read_text()
    lane = re.search(r'lane="([^"]+)"', text).group(1)
    (tmp_path / "fcd.xml").write_text(text.replace(f'lane="{lane}"', 'lane="elsewhere_0"', 1))
    with pytest.raises(UserError) as exc:
        read_fcd(tmp_path / "fcd.xml", section, m)
    _one_line(exc, tmp_path / "fcd.xml", r"row 1 \(line 4\), column 'lane'", "not on the section")


@pytest.mark.parametrize("fault", ["duplicated", "unsorted"])
def test_duplicated_or_unsorted_frame(
    fault: str, field_truth: Path, section: Section, tmp_path: Path
) -> None:
    m, _ = export.export_ngsim(field_truth, tmp_path / "n.csv")
    df = pd.read_csv(tmp_path / "n.csv")
    if fault == "duplicated":
        df = pd.concat([df.iloc[:6], df.iloc[5:6], df.iloc[6:]], ignore_index=True)
        want = r"row 7 \(line 8\), column 'Frame_ID'.*repeats"
    else:
        df.iloc[[4, 5]] = df.iloc[[5, 4]].to_numpy()
        want = r"row 6 \(line 7\), column 'Frame_ID'.*goes back"
    df.to_csv(tmp_path / "n.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_ngsim(tmp_path / "n.csv", section, m)
    _one_line(exc, tmp_path / "n.csv", want, "strictly increasing")


def test_station_off_the_section_or_not_placed(
    field_truth: Path, section: Section, tmp_path: Path
) -> None:
    m = export.export_pems(field_truth, tmp_path / "p.csv")
    missing = dataclasses.replace(m, stations=m.stations[1:])
    with pytest.raises(UserError) as exc:
        read_pems(tmp_path / "p.csv", section, missing)
    _one_line(exc, tmp_path / "p.csv", r"column 'Station'", "not placed on the section")
    off = (StationPlace(id=m.stations[0].id, arc_m=section.length_m + 50.0), *m.stations[1:])
    with pytest.raises(UserError) as exc:
        read_pems(tmp_path / "p.csv", section, dataclasses.replace(m, stations=off))
    _one_line(exc, tmp_path / "p.csv", "column 'arc_m'", "off the section")


def test_empty_interval(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m = field_export.export_generic_stations(field_truth, tmp_path / "s.csv")
    df = pd.read_csv(tmp_path / "s.csv")
    df.loc[3, "end_s"] = df.loc[3, "begin_s"]
    df.to_csv(tmp_path / "s.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_generic_stations(tmp_path / "s.csv", section, m, StationColumns(end="end_s"))
    _one_line(exc, tmp_path / "s.csv", r"row 4 \(line 5\), column 'end_s'", "empty interval")


def test_pems_speed_unit_and_text(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m = export.export_pems(field_truth, tmp_path / "p.csv")
    df = pd.read_csv(tmp_path / "p.csv", dtype=str)
    df.loc[2, "Lane 1 Avg Speed"] = "fast"
    df.to_csv(tmp_path / "p.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_pems(tmp_path / "p.csv", section, m)
    _one_line(
        exc,
        tmp_path / "p.csv",
        r"row 3 \(line 4\), column 'Lane 1 Avg Speed'",
        "'fast' is not a finite number",
    )


def test_negative_leader_spacing(field_truth: Path, section: Section, tmp_path: Path) -> None:
    m, _ = export.export_ngsim(field_truth, tmp_path / "n.csv")
    df = pd.read_csv(tmp_path / "n.csv")
    df.loc[df["Space_Headway"] > 0, "Space_Headway"] *= -1.0  # a sign flipped by an export
    df.to_csv(tmp_path / "n.csv", index=False)
    with pytest.raises(UserError) as exc:
        read_ngsim(tmp_path / "n.csv", section, m)
    _one_line(
        exc, tmp_path / "n.csv", r"row \d+ \(line \d+\)", "column 'Space_Headway'", "leader spacing"
    )
