"""The whole pipeline on networks the code has never seen, with small budgets.

* a corridor drawn by netgen from random parameters (edges, lengths, lanes, limits, demand
  and the seed itself come from a seeded generator): open, multi-lane, lane drops;
* the paper's ring driven by a user's own demand as a one-lane closed section.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import NETS, dump_toml

from macromicro_sumo.cli import main
from macromicro_sumo.sumo.netgen import random_corridor

SMALL_BUDGET = {
    "generator": {"epochs": 4, "snapshot_every_s": 10.0},
    "policy": {"updates": 2, "episodes_per_update": 8, "observation": "lookahead"},
    "evaluation": {"fcd_episodes": 2, "lf_trials": 2},  # leader-follower: 2 trials a method
    # The detector-calibrated IDM's fit re-runs the training runs per evaluation: two do.
    "deploy": {"calibration_evals": 2},
}


def _write(folder: Path, table: dict) -> Path:
    for name, sub in SMALL_BUDGET.items():
        table.setdefault(name, {}).update(sub)
    path = folder / f"{table['name']}.toml"
    path.write_text(dump_toml(table))
    return path


def _check_outputs(out: Path) -> pd.DataFrame:
    assert (out / "report.md").is_file()
    for png in ("time_space", "detectors", "distributions", "policy_training"):
        data = (out / "plots" / f"{png}.png").read_bytes()
        assert data[:4] == b"\x89PNG" and len(data) > 10_000, png
    align = pd.read_csv(out / "evaluation" / "macro_alignment.csv")
    methods = {"ground_truth", "policy", "micro_only", "macro_only", "idm_calibrated"}
    for label in ("estimated", "true"):
        assert set(align.loc[align["hidden_count"] == label, "method"]) == methods
    gt = align[align["method"] == "ground_truth"]
    assert (gt["mean_speed_err_mps"] == 0).all() and (gt["collisions"] == 0).all()
    assert np.isfinite(align["w1_speed_mps"]).all()
    micro = pd.read_csv(out / "evaluation" / "micro_consistency.csv")
    assert np.isfinite(micro.loc[micro["method"] == "policy", "nll"]).all()
    assert list((out / "evaluation" / "fcd").glob("*.fcd.xml"))
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(manifest["timings_s"]) >= {"simulate", "train_generator", "train_policy", "evaluate"}
    return align


def test_random_corridor_end_to_end(tmp_path: Path) -> None:
    rng = np.random.default_rng(20261121)
    cor = random_corridor(tmp_path / "net", int(rng.integers(1_000, 1_000_000)))
    table = {
        "name": "random_corridor",
        "seed": int(rng.integers(0, 1000)),
        "network": {"kind": "sumo", "sumocfg": str(cor.sumocfg)},
        "section": {"edges": list(cor.section_edges)},
        "instrumented": {"penetration": 0.3},
        "simulation": {"warmup_s": 200.0, "duration_s": 120.0, "n_runs": 4},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 200.0},
    }
    out = tmp_path / "run"
    assert main(["run", str(_write(tmp_path, table)), "--out", str(out), "--quiet"]) == 0
    align = _check_outputs(out)
    k = pd.read_csv(out / "evaluation" / "k_estimate_summary.csv")
    assert k.loc[k["runs"] == "all", "mean_abs_error_per_lane_veh"].iloc[0] < 3.0
    # A second run into the same folder skips every stage and reproduces the tables.
    assert main(["run", str(tmp_path / "random_corridor.toml"), "--out", str(out), "--quiet"]) == 0
    pd.testing.assert_frame_equal(align, pd.read_csv(out / "evaluation" / "macro_alignment.csv"))
    # What an edit redoes is the pipeline's one rule, tested on the ring
    # (tests/pipeline/test_pipeline.py): every scenario goes through it.


@pytest.mark.slow  # a closed one-lane section runs by default as ring_paper (test_pipeline.py)
def test_ring_as_a_closed_section_with_user_demand(tmp_path: Path) -> None:
    """Five IDM drivers on the paper's ring, looping by the ring's rerouters: the general
    path with a one-lane closed section."""
    routes = tmp_path / "ring.rou.xml"
    vehicles = "\n".join(
        f'    <vehicle id="v{i}" type="idm" route="r_e{i % 4}" depart="0" departPos="{20 + 7 * i}" '
        f'departSpeed="0"/>'
        for i in range(6)
    )
    routes.write_text(
        "<routes>\n"
        '    <vType id="idm" length="5" minGap="2" carFollowModel="IDM" accel="1.0" decel="1.5" '
        'tau="1.2" speedFactor="0.95" speedDev="0.05"/>\n'
        f"{vehicles}\n</routes>\n"
    )
    table = {
        "name": "ring_section",
        "seed": 3,
        "network": {
            "kind": "sumo",
            "net_file": str(NETS / "ring_r100_e4.net.xml"),
            "route_files": [str(routes)],
            "additional_files": [str(NETS / "ring_r100_e4.add.xml")],
        },
        "section": {"edges": ["e0", "e1", "e2", "e3"], "closed": True},
        "instrumented": {"ids": ["v0", "v2", "v4"]},
        "simulation": {"warmup_s": 60.0, "duration_s": 240.0, "n_runs": 4},
        "detectors": {"interval_s": 60.0, "auto_spacing_m": 150.0},
        # Every method is deployed on the random corridor; here the policy and the oracle.
        "deploy": {"methods": ["policy", "oracle"]},
    }
    out = tmp_path / "run"
    # Vehicles depart one after another on lane 0: the routes start on different edges.
    assert main(["run", str(_write(tmp_path, table)), "--out", str(out), "--quiet"]) == 0
    _check_outputs(out)
    traj = pd.read_csv(out / "ground_truth" / "trajectories.csv")
    # Closed: nobody leaves, every recorded step has the whole fleet on the section.
    assert (traj.groupby(["run", "time_s"]).size() == 6).all()
    assert set(traj.loc[traj["observed"], "vehicle_id"]) == {"v0", "v2", "v4"}
    k = pd.read_csv(out / "ground_truth" / "k_estimate.csv")
    assert (k["k_true"] == 3).all()
    # The leader-follower tests run round the loop and the report shows them.
    lf = pd.read_csv(out / "evaluation" / "leader_follower_summary.csv")
    assert {"policy", "idm_calibrated"} <= set(lf["method"])
    assert np.isfinite(lf["rmse_vs_idm_mps"]).all()
    # The reference follows itself; the IDM fitted to the same vehicles stays close and
    # collides nowhere (the two-update policies may: the test runs without a safety layer).
    idm = lf[lf["method"].isin(["IDM", "idm_calibrated"])]
    assert (
        not idm["collision"].any() and (lf.loc[lf["method"] == "IDM", "rmse_vs_idm_mps"] == 0).all()
    )
    assert lf.loc[lf["method"] == "idm_calibrated", "rmse_vs_idm_mps"].max() < 0.5
    report = (out / "report.md").read_text()
    assert "## Leader-follower (paper Fig. 3, on the section's lane path)" in report
    assert "reference: IDM fitted to every recorded vehicle" in report
    assert k["k_error"].abs().mean() <= 1.5


@pytest.mark.parametrize("kind", ["train-generator", "evaluate"])
def test_stage_commands_refuse_missing_inputs(tmp_path: Path, kind: str, capsys) -> None:
    cor = random_corridor(tmp_path / "net", 5)
    table = {
        "name": "c",
        "network": {"kind": "sumo", "sumocfg": str(cor.sumocfg)},
        "section": {"edges": list(cor.section_edges)},
    }
    path = _write(tmp_path, table)
    args = [kind, str(path), "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]
    if kind == "evaluate":
        args += ["--generator", str(tmp_path / "g.pt"), "--policy", str(tmp_path / "p.pt")]
    assert main([*args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and ("missing" in err or "not found" in err)
    assert not (tmp_path / "o").exists()
