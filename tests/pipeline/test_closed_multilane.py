"""A closed multi-lane section drawn from a seed: radius, lanes and fleet size vary.

The paper's ring is the closed one-lane case; this is the same road model with more lanes,
where SUMO changes lanes and the section stages (not the ring's) do all the work.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from conftest import dump_toml

from macromicro_sumo.cli import main
from macromicro_sumo.road.ring import build_ring


def _fleet_xml(rng: np.random.Generator, n_edges: int, lanes: int, edge_m: float, n: int) -> str:
    types = (
        '    <vType id="car" carFollowModel="IDM" length="5" minGap="2" accel="2.6" decel="4.5" '
        'tau="1.2" maxSpeed="30" speedDev="0.1"/>\n'
        '    <vType id="van" carFollowModel="Krauss" length="7" minGap="2.5" accel="1.5" '
        'decel="4" tau="1.4" maxSpeed="12"/>\n'
    )
    per_edge = int(np.ceil(n / n_edges))
    rows = []
    for k in range(n):
        edge, j = divmod(k, per_edge)
        vtype = "van" if rng.random() < 0.2 else "car"
        pos = 5.0 + j * (edge_m - 10.0) / per_edge
        rows.append(
            f'    <vehicle id="v{k}" type="{vtype}" route="r_e{edge}" depart="0" '
            f'departLane="{k % lanes}" departPos="{pos:.1f}" departSpeed="0"/>'
        )
    return "<routes>\n" + types + "\n".join(rows) + "\n</routes>\n"


def test_closed_multilane_section_end_to_end(tmp_path: Path) -> None:
    rng = np.random.default_rng(20261124)
    radius, lanes = float(rng.uniform(60.0, 120.0)), int(rng.integers(2, 4))
    edge_m = 2 * np.pi * radius / 4
    n = int(2 * np.pi * radius * lanes / rng.uniform(25.0, 45.0))  # 25-45 m per vehicle and lane
    net, add = build_ring(radius, 4, tmp_path / "net", "ring", lanes=lanes)
    routes = tmp_path / "net" / "fleet.rou.xml"
    routes.write_text(_fleet_xml(rng, 4, lanes, edge_m, n))
    table = {
        "name": "closed_multilane",
        "seed": 3,
        "network": {
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(routes)],
            "additional_files": [str(add)],
        },
        "section": {"edges": ["e0", "e1", "e2", "e3"], "closed": True},
        "instrumented": {"penetration": 0.2},
        "simulation": {"warmup_s": 60.0, "duration_s": 120.0, "n_runs": 3},
        "detectors": {"auto_spacing_m": 100.0},
        "bounds": {"accel_mps2": [-4.5, 2.6], "min_gap_m": 2.0},
        "generator": {"epochs": 4, "snapshot_every_s": 10.0},
        "policy": {"updates": 2, "episodes_per_update": 8, "observation": "lookahead"},
        "evaluation": {"fcd_episodes": 1, "lf_trials": 2},
        # The policy and the oracle (every method is deployed on test_section_pipeline's
        # random corridor); the deploy figures of 30 s: they took half the test's time.
        "deploy": {"methods": ["policy", "oracle"], "fcd_s": 30.0},
    }
    path = tmp_path / "closed_multilane.toml"
    path.write_text(dump_toml(table))
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0

    runs = pd.read_csv(out / "ground_truth" / "runs.csv")
    assert (runs["collisions"] == 0).all() and (runs["teleports"] == 0).all()
    assert (runs["vehicles_seen"] == n).all()  # nobody leaves a closed section
    traj = pd.read_csv(out / "ground_truth" / "trajectories.csv")
    assert set(traj["lane_index"]) == set(range(lanes))  # SUMO uses every lane
    align = pd.read_csv(out / "evaluation" / "macro_alignment.csv")
    assert {"ground_truth", "policy", "micro_only", "macro_only", "idm_calibrated"} <= set(
        align["method"]
    )
    gt = align[align["method"] == "ground_truth"]
    assert (gt["mean_speed_err_mps"] == 0).all() and (gt["collisions"] == 0).all()
    k = pd.read_csv(out / "ground_truth" / "k_estimate.csv")
    # On a closed road the detectors see the whole fleet: the hidden count is within one
    # vehicle per lane.
    assert k["k_error"].abs().mean() <= lanes
    report = (out / "report.md").read_text()
    # The methods registry describes every method of the table; the ring's oracle is absent.
    assert "- `idm_calibrated` (baseline): one IDM fitted by least squares" in report
    assert "`idm_true`" not in report
    manifest = json.loads((out / "manifest.json").read_text())
    assert "evaluate" in manifest["timings_s"]
    deployed = pd.read_csv(out / "deploy" / "deploy_summary.csv")
    assert set(deployed["method"]) == {"policy", "oracle"}
