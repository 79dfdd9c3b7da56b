"""Round trips: a simulated ground truth exported into every layout and read back.

Exact layouts (FCD, highD, generic CSV; E1 XML, generic station CSV) give back positions
within 0.05 m (measured: 5e-5 m, the 4 written decimals) and speeds, flows and occupancy
per station-interval as written. PeMS rounds speeds to 0.1 mph (0.022 m/s) and occupancy to
4 decimals of a fraction. NGSIM gets 0.3 m Gaussian position noise; the sEMA cleaning gives
speeds back with an RMSE of 0.24-0.25 m/s (seeds 0-2; the file's own differenced speeds:
0.47 m/s) and accelerations with 0.51-0.52 m/s^2 (0.92 differenced).
"""

from __future__ import annotations

from pathlib import Path

import field_export
import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.fielddata import export
from macromicro_sumo.fielddata.cleaning import NGSIM_CLEANING, clean_trajectories
from macromicro_sumo.fielddata.schema import DET_COLUMNS, TRAJ_COLUMNS
from macromicro_sumo.fielddata.stations import (
    read_generic_stations,
    read_pems,
    read_sumo_detectors,
)
from macromicro_sumo.fielddata.trajectories import (
    read_fcd,
    read_generic_trajectories,
    read_highd,
    read_ngsim,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.data import StationColumns, TrajectoryColumns

POSITION_TOL_M = 0.05
NGSIM_SPEED_RMSE = 0.30  # measured 0.24-0.25 m/s
NGSIM_ACCEL_RMSE = 0.60  # measured 0.51-0.52 m/s^2


def _matched(frame: pd.DataFrame, truth: pd.DataFrame, ids: dict[str, int] | None) -> pd.DataFrame:
    if ids is not None:
        back = {str(v): k for k, v in ids.items()}
        frame = frame.assign(vehicle_id=frame["vehicle_id"].map(back))
    both = frame.merge(truth, on=["vehicle_id", "time_s"], suffixes=("", "_t"))
    assert len(both) == len(truth) == len(frame)
    return both


@pytest.mark.parametrize("layout", ["fcd", "highd", "generic"])
def test_exact_trajectory_layouts_round_trip(
    layout: str, field_truth: Path, section: Section, observed: pd.DataFrame, tmp_path: Path
) -> None:
    ids = None
    if layout == "fcd":
        m = field_export.export_fcd(field_truth, tmp_path / "fcd.xml")
        got = read_fcd(tmp_path / "fcd.xml", section, m)
    elif layout == "highd":
        m, ids = field_export.export_highd(field_truth, tmp_path / "tracks.csv")
        got = read_highd(tmp_path / "tracks.csv", section, m)
    else:
        m = field_export.export_generic_trajectories(field_truth, tmp_path / "t.csv")
        got = read_generic_trajectories(tmp_path / "t.csv", section, m)
    assert tuple(got.frame.columns[: len(TRAJ_COLUMNS)]) == TRAJ_COLUMNS
    assert got.frame["observed"].all()
    # highD carries the vehicle's leader; the generic CSV's default column map reads none.
    assert got.leader_measured == (layout == "highd")
    both = _matched(got.frame, observed, ids)
    assert np.abs(both["arc_m"] - both["arc_m_t"]).max() < POSITION_TOL_M
    assert (both["lane_index"] == both["lane_index_t"]).all()
    assert (both["edge_index"] == both["edge_index_t"]).all()
    assert np.abs(both["speed_mps"] - both["speed_mps_t"]).max() < 1e-3
    assert np.abs(both["accel_mps2"] - both["accel_mps2_t"]).max() < 1e-3


@pytest.mark.parametrize("layout", ["highd", "generic", "ngsim"])
def test_measured_leaders_round_trip(
    layout: str, field_truth: Path, section: Section, tmp_path: Path
) -> None:
    """Each observed row's true leader (hidden or not) comes back: its spacing and speed
    exactly from highD (bumper gap + the leader's length) and the generic CSV, from NGSIM
    within the radar noise (0.3 m) with the speed derived from the smoothed gap."""
    _, truth = export.observed_rows(field_truth)
    assert (truth["leader_id"] != "").mean() > 0.5  # most rows have a vehicle ahead
    hidden = ~truth["leader_id"].isin(set(truth["vehicle_id"])) & (truth["leader_id"] != "")
    assert hidden.mean() > 0.2  # and often it is not an observed one
    ids = dict(zip(truth["vehicle_id"], truth["number"], strict=False))
    if layout == "highd":
        m, ids = field_export.export_highd(field_truth, tmp_path / "tracks.csv")
        got = read_highd(tmp_path / "tracks.csv", section, m).frame
    elif layout == "generic":
        field_export.export_generic_trajectories(field_truth, tmp_path / "t.csv")
        cols = TrajectoryColumns(
            leader_id="leader_id", spacing="spacing_m", leader_speed="leader_speed_mps"
        )
        got = read_generic_trajectories(tmp_path / "t.csv", section, columns=cols).frame
        ids = None
    else:
        m, ids = export.export_ngsim(field_truth, tmp_path / "n.csv", noise_m=0.3, seed=0)
        raw = read_ngsim(tmp_path / "n.csv", section, m)
        assert raw.frame["leader_speed_mps"].isna().all()  # NGSIM has none: derived
        got = clean_trajectories(raw, NGSIM_CLEANING).frame
    both = _matched(got, truth, ids)
    ahead = both["leader_id_t"] != ""
    assert (both["leader_spacing_m"].notna() == ahead).all()
    d_space = (both["leader_spacing_m"] - both["spacing_m"])[ahead]
    d_speed = (both["leader_speed_mps"] - both["leader_speed_mps_t"])[ahead]
    if layout == "ngsim":
        assert d_space.std() == pytest.approx(0.3, abs=0.03)  # the radar noise
        assert np.abs(d_space.mean()) < 0.03
        # Own speed + d gap / dt, both smoothed: about the own speed's error (0.24 m/s)
        # twice over; a leader change inside a sample pair is a jump, not a speed.
        assert np.sqrt((d_speed**2).median()) < NGSIM_SPEED_RMSE * 2
        assert np.sqrt((d_speed**2).mean()) < 1.0
    else:
        # highD numbers every vehicle of the recording, hidden leaders too.
        want = both["leader_number"].astype(str) if ids else both["leader_id_t"]
        assert (both.loc[ahead, "leader_id"] == want[ahead]).all()
        assert np.abs(d_speed).max() < 1e-3
        # highD gives the bumper gap: a hidden leader's length is the file's median one.
        known = both.loc[ahead, "leader_id_t"].isin(set(truth["vehicle_id"]))
        known |= layout == "generic"
        assert np.abs(d_space[known]).max() < 1e-3
        assert np.abs(d_space).max() <= np.ptp(truth["length_m"]) + 1e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_ngsim_round_trip_within_the_noise_after_smoothing(
    seed: int, field_truth: Path, section: Section, observed: pd.DataFrame, tmp_path: Path
) -> None:
    m, ids = export.export_ngsim(field_truth, tmp_path / "ngsim.csv", noise_m=0.3, seed=seed)
    raw = read_ngsim(tmp_path / "ngsim.csv", section, m)
    clean = clean_trajectories(raw, NGSIM_CLEANING)
    noisy = _matched(raw.frame, observed, ids)
    both = _matched(clean.frame, observed, ids)
    # Lanes counted from the left depend on the lane count there: noise that carries a
    # position across a junction where it changes gives another lane index, nowhere else.
    wrong = both.loc[both["lane_index"] != both["lane_index_t"], "arc_m_t"].to_numpy()
    ends = np.concatenate([section.offsets_m, section.offsets_m + section.lengths_m])
    assert len(wrong) < 0.01 * len(both)
    assert all(np.abs(ends - a).min() < 1.5 for a in wrong)
    assert (both["arc_m"] - both["arc_m_t"]).std() == pytest.approx(0.3, abs=0.03)  # the noise

    def rmse(d: pd.DataFrame, c: str) -> float:
        return float(np.sqrt(((d[c] - d[c + "_t"]) ** 2).mean()))

    assert rmse(both, "speed_mps") < NGSIM_SPEED_RMSE < rmse(noisy, "speed_mps")
    assert rmse(both, "accel_mps2") < NGSIM_ACCEL_RMSE < rmse(noisy, "accel_mps2")
    assert not clean.flags[["accel_outlier", "speed_jump", "after_gap"]].any().any()


def _check_stations(
    got: pd.DataFrame, det: pd.DataFrame, keys: list[str], speed_tol: float
) -> None:
    assert tuple(got.columns[: len(DET_COLUMNS)]) == DET_COLUMNS
    both = got.merge(det, on=keys, suffixes=("", "_t"))
    assert len(both) == len(det) == len(got)
    for col in {"lane_index", "arc_m"} - set(keys):
        assert np.abs(both[col] - both[col + "_t"]).max() < POSITION_TOL_M
    assert (both["n_veh"] == both["n_veh_t"]).all()
    np.testing.assert_allclose(both["flow_vph"], both["flow_vph_t"], atol=1e-6)
    assert (both["speed_mps"].isna() == both["speed_mps_t"].isna()).all()
    assert np.nanmax(np.abs(both["speed_mps"] - both["speed_mps_t"])) <= speed_tol
    np.testing.assert_allclose(both["occupancy_pct"], both["occupancy_pct_t"], atol=0.006)


def test_e1_xml_round_trip(
    field_truth: Path, section: Section, detectors: pd.DataFrame, tmp_path: Path
) -> None:
    m = field_export.export_e1_xml(field_truth, tmp_path / "e1.xml", tmp_path / "det.add.xml")
    got = read_sumo_detectors(tmp_path / "e1.xml", section, tmp_path / "det.add.xml", m)
    _check_stations(got.frame, detectors, ["detector_id", "begin_s"], 0.006)


def test_generic_station_csv_round_trip(
    field_truth: Path, section: Section, detectors: pd.DataFrame, tmp_path: Path
) -> None:
    m = field_export.export_generic_stations(field_truth, tmp_path / "st.csv")
    cols = StationColumns(end="end_s", occupancy="occupancy")
    got = read_generic_stations(tmp_path / "st.csv", section, m, cols)
    _check_stations(got.frame, detectors, ["detector_id", "begin_s"], 1e-4)
    np.testing.assert_allclose(got.frame["density_vpkm"], detectors["density_vpkm"], atol=1e-4)


def test_pems_round_trip_within_rounding(
    field_truth: Path, section: Section, detectors: pd.DataFrame, tmp_path: Path
) -> None:
    m = export.export_pems(field_truth, tmp_path / "pems.csv")
    got = read_pems(tmp_path / "pems.csv", section, m)
    # PeMS names a station, not a loop: match on lane, position and interval.
    _check_stations(got.frame, detectors, ["lane_index", "arc_m", "begin_s"], 0.05 * 0.44704 + 1e-9)
    assert got.quality["observed_pct"].eq(100.0).all()


# E2 against the recorded trajectories (measured on the e2_truth fixture, 16 detector-
# intervals with traffic): SUMO counts a vehicle partly on the area, once per step, with the
# state at time t in the interval holding t, as here; but the recorder puts a vehicle whose
# front has crossed into the junction on the lane it leads to, so a tail still on the
# area's last metres is not counted here. The reader's density (SUMO's count less the
# occupancy, fronts on the area) is -5.1..+3.1 % of the fronts counted here (at most 0.22
# veh/km), the time-mean speed within 0.095 m/s (2 decimals written, the same rows).
E2_DENSITY_REL_TOL = 0.08
E2_DENSITY_ABS_TOL_VPKM = 0.3
# On the user's 150 m areas (not to the lane's end) entries and exits weigh more: SUMO counts
# the fraction of a step a vehicle spends on the area, this side whole steps: within
# 0.17 m/s measured (0.7% of ~25 m/s).
E2_SPEED_TOL_MPS = 0.25


def _e2_truth(
    traj: pd.DataFrame, section: Section, row: pd.Series, dt: float
) -> tuple[float, float]:
    """(density veh/km, time-mean speed m/s) of the recorded vehicles on one E2's area in one
    interval: the speed over the vehicles with any part on the area (SUMO's rule), the
    density from those whose front is on it (the reader takes SUMO's count less the
    occupancy: a vehicle once, not twice where it straddles two areas)."""
    steps = traj[
        (traj["time_s"] > row["begin_s"] - dt / 2) & (traj["time_s"] < row["end_s"] - dt / 2)
    ]
    n_steps = steps["time_s"].nunique()
    e = steps["edge_index"].to_numpy()
    on_edge = steps["arc_m"].to_numpy() <= section.offsets_m[e] + section.lengths_m[e]
    on = (
        on_edge
        & (steps["lane_index"] == row["lane_index"])
        & (steps["arc_m"] > row["arc_m"])
        & (steps["arc_m"] - steps["length_m"] < row["arc_m"] + row["length_m"])
    )
    speed = steps.loc[on, "speed_mps"].mean() if on.any() else np.nan
    front = on & (steps["arc_m"] <= row["arc_m"] + row["length_m"])
    return front.sum() / n_steps / row["length_m"] * 1000.0, speed


def test_e2_xml_round_trip(e2_truth: Path) -> None:
    """SUMO's own E2 output of a run, read back with the definitions SUMO ran, against the
    same run's recorded trajectories."""
    section = Section.read(e2_truth / "section.json")
    run = e2_truth / "sumo" / "run_000"
    got = read_sumo_detectors(run / "e2.xml", section, run / "detectors.add.xml").frame
    assert tuple(got.columns[: len(DET_COLUMNS)]) == DET_COLUMNS
    assert (got["kind"] == "e2").all()
    # Placed where the user's file puts them: pos 50 m on each lane, 150 m long (the truth
    # stage once rewrote them as lanes= + length=, which SUMO runs to the lane's end).
    for r in got.drop_duplicates("detector_id").itertuples():
        lane_id = r.detector_id.removeprefix("e2_")
        lane, arc = section.locate(lane_id, 50.0)  # type: ignore[misc]
        assert (r.lane_index, r.arc_m) == (lane, pytest.approx(arc, abs=1e-6))
        assert r.length_m == pytest.approx(150.0, abs=1e-6)
    traj = pd.read_csv(e2_truth / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    vt = pd.read_csv(e2_truth / "vtypes.csv", dtype={"vtype": str})
    traj["length_m"] = traj["vtype"].map(dict(zip(vt["vtype"], vt["length_m"], strict=True)))
    dt = float(np.diff(np.unique(traj["time_s"])).min())
    recorded = got[
        (got["begin_s"] >= traj["time_s"].min() - dt) & (got["end_s"] <= traj["time_s"].max())
    ]
    assert len(recorded) == 4 * got["detector_id"].nunique()  # 120 s in 30 s intervals
    truth = np.array([_e2_truth(traj, section, r, dt) for _, r in recorded.iterrows()])
    k, v = recorded["density_vpkm"].to_numpy(), recorded["speed_mps"].to_numpy()
    assert (k > 0).sum() >= 12  # most lanes carry traffic: not a comparison of zeros
    np.testing.assert_allclose(
        k, truth[:, 0], rtol=E2_DENSITY_REL_TOL, atol=E2_DENSITY_ABS_TOL_VPKM
    )
    assert (np.isnan(v) == np.isnan(truth[:, 1])).all()
    assert np.nanmax(np.abs(v - truth[:, 1])) <= E2_SPEED_TOL_MPS
