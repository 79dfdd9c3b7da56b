"""The ground truth of the paper's ring (a ring file: the closed one-lane section of its
generated net, the IDM fleet as its demand) against real SUMO: geometry, determinism,
detector accuracy, and SUMO's IDM against the textbook model."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SMALL, write_scenario
from ring_reference import simulate_idm_ring

from macromicro_sumo.cli import main
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

L = 2 * math.pi * 100.0  # R = 100 m
N = 5


def circular_diff(a: np.ndarray, b: np.ndarray, length_m: float = L) -> np.ndarray:
    return np.mod(a - b + length_m / 2, length_m) - length_m / 2


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple:
    """The paper ring, 2 runs of 120 s, simulated once through the CLI."""
    folder = tmp_path_factory.mktemp("small")
    path = write_scenario(folder, SMALL)
    out = folder / "out"
    assert main(["simulate", str(path), "--out", str(out), "--quiet"]) == 0
    return load_scenario(path), out


@pytest.fixture(scope="module")
def traj(small) -> pd.DataFrame:
    return pd.read_csv(small[1] / "trajectories.csv", dtype={"vehicle_id": str})


def test_every_vehicle_every_step_and_spacings_sum_to_the_ring(small, traj):
    sc, _ = small
    n_steps = round(sc.simulation.duration_s / sc.simulation.step_length_s)
    assert len(traj) == sc.simulation.n_runs * N * n_steps
    assert traj["arc_m"].between(0, L).all() and (traj["lane_index"] == 0).all()
    for _, step in traj.groupby(["run", "time_s"]):
        arc = np.sort(step["arc_m"].to_numpy())
        spacing = np.diff(np.append(arc, arc[0] + L))
        assert spacing.sum() == pytest.approx(L, abs=1e-4)
        assert spacing.min() > 5.0  # no overlap (vehicles are 5 m long)


def test_no_collisions_or_teleports(small):
    runs = pd.read_csv(small[1] / "runs.csv")
    assert len(runs) == small[0].simulation.n_runs
    assert (runs["collisions"] == 0).all() and (runs["teleports"] == 0).all()


def test_first_recorded_state_is_the_sampled_initial_state(small, traj):
    vehicles = pd.read_csv(small[1] / "vehicles.csv", dtype={"vehicle_id": str})
    vehicles = vehicles.set_index(["run", "vehicle_id"])
    first = traj[traj["time_s"] == traj.groupby("run")["time_s"].transform("min")]
    first = first.set_index(["run", "vehicle_id"]).loc[vehicles.index]
    assert len(first) == len(vehicles) == small[0].simulation.n_runs * N
    err = circular_diff(first["arc_m"].to_numpy(), vehicles["initial_arc_m"].to_numpy())
    assert np.abs(err).max() < 0.01
    assert np.abs(first["speed_mps"] - vehicles["initial_speed_mps"]).max() < 0.01


def test_same_seed_gives_identical_csv_bytes(small, tmp_path):
    sc, out = small
    again = simulate_section(sc, tmp_path / "again", progress=False)
    names = sorted(p.name for p in out.glob("*.csv"))
    assert "trajectories.csv" in names and "macro.csv" in names
    assert sorted(p.name for p in again.glob("*.csv")) == names
    for name in names:
        assert (out / name).read_bytes() == (again / name).read_bytes(), name


def test_different_seed_gives_different_trajectories(small, traj, tmp_path):
    sc, _ = small
    other = load_scenario(write_scenario(tmp_path, {**SMALL, "seed": sc.seed + 1}))
    out = simulate_section(other, tmp_path / "other", progress=False)
    traj2 = pd.read_csv(out / "trajectories.csv")
    assert traj2.shape == traj.shape
    assert not np.allclose(traj2["arc_m"], traj["arc_m"])


def test_detectors_agree_with_trajectories(small):
    """The ring's loops (E1 at mid-edge, E2 over every edge) against the trajectories, for
    every run and interval: the mean speed within 3%."""
    sc, out = small
    m = pd.read_csv(out / "macro.csv")
    det = m[m["source"] == "detectors"].set_index(["run", "begin_s"]).sort_index()
    tru = m[m["source"] == "trajectories"].set_index(["run", "begin_s"]).sort_index()
    assert len(tru) == sc.simulation.n_runs * int(
        sc.simulation.duration_s // sc.detectors.interval_s
    )
    assert det.index.tolist() == tru.index.tolist()
    rel = (det["mean_speed_mps"] / tru["mean_speed_mps"] - 1).abs()
    assert rel.notna().all() and rel.max() <= 0.03


def test_sumo_idm_matches_textbook_idm_with_uniform_limits(tmp_path: Path, make_scenario):
    """SUMO's IDM equals the Euler IDM of physics.simulate_idm_ring over 100 s.

    Needs uniform limits (no look-ahead braking), 4-decimal speed factors (SUMO rounds
    them) and leaders within SUMO's look-ahead, hence 10 vehicles starting ~63 m apart.
    """
    limit = 13.0
    sc = load_scenario(
        make_scenario(
            {
                "fleet.n_vehicles": 10,
                "fleet.accel_mps2": [0.3, 0.6],
                "fleet.decel_mps2": [1.0, 1.5],
                "fleet.tau_s": [1.0, 1.8],
                "fleet.speed_factor": [0.85, 1.0],
                "speed_limits.range_mps": [limit, limit],
                "initial.speed_mps": [10.5, 12.0],
                "initial.min_spacing_m": 55.0,
                "initial.spacing_concentration": 1000.0,
                "simulation.duration_s": 100.0,
                "simulation.n_runs": 2,
            }
        )
    )
    out = simulate_section(sc, tmp_path / "out", progress=False)
    traj = pd.read_csv(out / "trajectories.csv", dtype={"vehicle_id": str})
    traj = traj[traj["run"] == 0]
    p = pd.read_csv(out / "vehicles.csv", dtype={"vehicle_id": str})
    p = p[p["run"] == 0].set_index("vehicle_id")
    ids = sorted(p.index, key=lambda v: int(v.removeprefix("v")))
    p = p.loc[ids]
    arc = traj.pivot(index="time_s", columns="vehicle_id", values="arc_m")[ids].to_numpy()
    speed = traj.pivot(index="time_s", columns="vehicle_id", values="speed_mps")[ids].to_numpy()
    params = {
        "desired_speed_mps": np.minimum(p["max_speed_mps"], p["speed_factor"] * limit).to_numpy(),
        "tau_s": p["tau_s"].to_numpy(),
        "accel_mps2": p["accel_mps2"].to_numpy(),
        "decel_mps2": p["decel_mps2"].to_numpy(),
        "min_gap_m": p["min_gap_m"].to_numpy(),
        "delta": float(p["delta"].iloc[0]),
    }
    length = float(L)
    want_arc, want_speed = simulate_idm_ring(
        arc[0], speed[0], length, sc.fleet.length_m, params, 0.5, len(arc) - 1
    )
    assert np.abs(want_speed - speed).max() < 1e-5
    assert np.abs(circular_diff(want_arc, arc, length)).max() < 1e-4
    # The fleet actually interacted: speeds changed by more than rounding.
    assert np.ptp(speed, axis=0).max() > 0.1
