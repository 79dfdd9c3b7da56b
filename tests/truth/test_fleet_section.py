"""The IDM fleet as the demand of a closed one-lane section: a ring file and the section
table spelled out (its own detectors) drive the same vehicles, with the same draws."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import NETS, dump_toml, scenario_table

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import load_section, simulate_section

# Small: 2 runs of 60 s, 4 vehicles (a few seconds of SUMO each).
RING = {"simulation.n_runs": 2, "simulation.duration_s": 60.0, "fleet.n_vehicles": 4}
RING.update({"detectors.interval_s": 30.0, "bounds.spacing_m": [100.0, 200.0]})
RING.update({"generator.hidden_train": [0, 3], "generator.hidden_eval": [1, 3]})


def section_table(ring: dict, **network) -> dict:
    """The ring scenario as a section scenario: the ring's net, its four edges closed, the
    ring's [fleet], [speed_limits] and [initial] as the demand."""
    return {
        "name": "ring_as_section",
        "seed": ring["seed"],
        "network": {"kind": "sumo", "net_file": ring["network"]["net_file"], **network},
        "section": {"edges": ["e0", "e1", "e2", "e3"], "closed": True},
        "instrumented": {"penetration": 0.5},
        "simulation": {
            "step_length_s": ring["simulation"]["step_length_s"],
            "warmup_s": 0.0,
            "duration_s": ring["simulation"]["duration_s"],
            "n_runs": ring["simulation"]["n_runs"],
        },
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 157.0},
        "fleet": ring["fleet"],
        "speed_limits": ring["speed_limits"],
        "initial": ring["initial"],
    }


def write(path: Path, table: dict) -> Path:
    path.write_text(dump_toml(table))
    return path


@pytest.fixture(scope="module")
def truths(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, SectionScenario]:
    tmp = tmp_path_factory.mktemp("fleet")
    ring = scenario_table(RING)
    ring_sc = load_scenario(write(tmp / "ring.toml", ring))
    sec_sc = load_scenario(write(tmp / "section.toml", section_table(ring)))
    assert isinstance(sec_sc, SectionScenario)
    ring_out = simulate_section(ring_sc, tmp / "ring_truth", progress=False)
    sec_out = simulate_section(sec_sc, tmp / "section_truth", progress=False)
    return ring_out, sec_out, sec_sc


def test_a_ring_file_and_its_section_table_drive_the_same_vehicles(truths):
    ring_out, sec_out, _ = truths
    ring = pd.read_csv(ring_out / "trajectories.csv", dtype={"vehicle_id": str})
    sec = pd.read_csv(sec_out / "trajectories.csv", dtype={"vehicle_id": str})
    keys = ["run", "time_s", "vehicle_id"]
    ring, sec = ring.sort_values(keys).reset_index(), sec.sort_values(keys).reset_index()
    # The same rows: every vehicle at every step of both runs, on the same time grid.
    assert len(ring) == len(sec) == 2 * 120 * 4
    assert (ring[keys].to_numpy() == sec[keys].to_numpy()).all()
    # The same states: identical draws, SUMO seeds and vTypes (the detectors differ: the
    # ring's E1/E2 file against loops every 157 m; they do not move a vehicle).
    assert np.abs(ring["arc_m"] - sec["arc_m"]).max() < 1e-6
    assert np.abs(ring["speed_mps"] - sec["speed_mps"]).max() < 1e-6
    # And the dynamics are not trivial: the fleet changes speed away from equilibrium.
    assert ring.groupby("vehicle_id")["speed_mps"].agg(np.ptp).min() > 0.1
    # The draws written beside them are the ring's, run by run.
    for name in ("vehicles.csv", "speed_limits.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(ring_out / name), pd.read_csv(sec_out / name))
    seeds = [pd.read_csv(o / "runs.csv")["sumo_seed"].tolist() for o in (ring_out, sec_out)]
    assert seeds[0] == seeds[1]
    assert pd.read_csv(sec_out / "runs.csv")["collisions"].sum() == 0


def test_section_truth_of_a_fleet_marks_instrumented_vehicles_per_run(truths):
    _, sec_out, sc = truths
    sec = pd.read_csv(sec_out / "trajectories.csv", dtype={"vehicle_id": str})
    per_vehicle = sec.groupby(["run", "vehicle_id"])["observed"].nunique()
    assert (per_vehicle == 1).all()  # a vehicle is instrumented for a whole run or not at all
    vt = pd.read_csv(sec_out / "vtypes.csv")
    assert sorted(vt["vtype"]) == [f"v{i}" for i in range(sc.fleet.n_vehicles)]
    assert (vt["car_follow_model"] == "IDM").all() and (vt["length_m"] == 5.0).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"section": {"edges": ["e0", "e1", "e2", "e3"], "closed": False}}, "closed section"),
        ({"drop": "initial"}, r"missing \[initial\]"),
        ({"route_files": True}, "route_files and network.sumocfg are not accepted"),
        ({"fleet.n_vehicles": 130}, "does not fit on a 628.32 m section"),
        ({"two_lanes": True}, "drives one lane"),
    ],
)
def test_a_fleet_demand_refuses_what_it_cannot_drive(tmp_path, change, message):
    table = section_table(scenario_table(RING))
    if "section" in change:
        table["section"] = change["section"]
    if "drop" in change:
        del table[change["drop"]]
    if "route_files" in change:
        table["network"]["route_files"] = [str(NETS / "ring2_r100" / "ring2.rou.xml")]
    if "fleet.n_vehicles" in change:
        table["fleet"] = {**table["fleet"], "n_vehicles": change["fleet.n_vehicles"]}
        table["initial"] = {**table["initial"], "min_spacing_m": 5.0}
    if "two_lanes" in change:
        table["network"]["net_file"] = str(NETS / "ring2_r100" / "ring2_r100_e4.net.xml")
    with pytest.raises(UserError, match=message) as err:
        load_section(load_scenario(write(tmp_path / "s.toml", table)))
    assert "\n" not in str(err.value)
