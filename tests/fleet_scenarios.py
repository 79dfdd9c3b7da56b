"""A small ring_paper_section for the tests: the ring's heterogeneous IDM fleet as the demand
of the ring network read as a closed one-lane section, every vehicle recorded, tiny budgets
for every stage (real SUMO runs of a few seconds)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from conftest import NETS, dump_toml


def small_fleet_table(
    n_vehicles: int = 4, n_runs: int = 4, hidden: str = "snapshot", **tables: dict[str, Any]
) -> dict[str, Any]:
    """The scenario as a TOML table: ``n_runs`` runs of 60 s, 30 s detector intervals;
    ``tables`` update the named tables (``deploy={...}``)."""
    table: dict[str, Any] = {
        "name": "small_fleet",
        "seed": 2024,
        "network": {
            "kind": "sumo",
            "net_file": str(NETS / "ring_r100_e4.net.xml"),
            "additional_files": [str(NETS / "ring_r100_e4.det.add.xml")],
        },
        "section": {"edges": ["e0", "e1", "e2", "e3"], "closed": True},
        "instrumented": {"hidden": hidden, "penetration": 0.5},
        "simulation": {"warmup_s": 0.0, "duration_s": 60.0, "n_runs": n_runs},
        "detectors": {"interval_s": 30.0, "use_user": True},
        "bounds": {"accel_mps2": [-1.1, 0.5], "min_gap_m": 2.0},
        "generator": {
            "k_source": "truth",
            "snapshot_every_s": 5.0,
            "epochs": 2,
            "hidden_train": [0, n_vehicles],
            "hidden_eval": [1, n_vehicles - 1],
        },
        "policy": {
            "updates": 1,
            "episodes_per_update": 8,
            "horizon": 4,
            "hidden_train": [1, 3],
            "observation": "lookahead",
        },
        "evaluation": {"horizon_steps": 4, "fcd_episodes": 0, "lf_trials": 2},
        "fleet": {
            "n_vehicles": n_vehicles,
            "length_m": 5.0,
            "accel_mps2": [0.8, 1.2],
            "decel_mps2": [1.2, 1.8],
            "tau_s": [1.0, 1.6],
            "min_gap_m": [2.0, 3.0],
            "delta": 4.0,
            "speed_factor": [0.93, 0.98],
            "max_speed_mps": [50.0, 50.0],
        },
        "speed_limits": {"range_mps": [12.0, 14.0], "step_mps": 0.5},
        "initial": {"speed_mps": [10.5, 13.5], "spacing_concentration": 7.0, "min_spacing_m": 60.0},
    }
    for name, values in tables.items():
        table[name] = {**table.get(name, {}), **values}
    return table


def write_fleet_scenario(folder: Path, table: dict[str, Any], name: str = "fleet.toml") -> Path:
    path = folder / name
    path.write_text(dump_toml(table))
    return path
