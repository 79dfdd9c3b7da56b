"""The ring wing's leader-follower tests against the section version on the same ring (issue 16).

Runs ``evaluation.ring.leader_follower_tests`` (``RingCore`` on ``scenarios/ring_paper.toml``)
and ``evaluation.leader_follower_section.run_leader_follower_for`` (``SectionCore`` on the
net of ``scenarios/ring_paper_section.toml``, read as a closed section) with the same
followers: the policies of ``--run`` (``policy/policy.pt``, ``policy/policy_micro_only.pt``),
the IDM calibrated on its ground truth's train + val runs as the evaluate stage does, the
fleet's IDM as reference, ``evaluation.lf_trials`` trials, seed ``scenario.seed``. Prints
both tables (mean RMSE against IDM, smallest gap, collisions per scenario and method) and
the largest difference between the two sets of traces.

    python scripts/lf_ring_vs_section.py --run runs/ring_paper

``--run`` is the output folder of ``macromicro run scenarios/ring_paper.toml`` (or of its
ground-truth, generator and policy stages alone).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from macromicro_sumo.data.ring import load_ground_truth, split_runs
from macromicro_sumo.evaluation.ring import leader_follower_tests, micro_pairs

from macromicro_sumo.evaluation import leader_follower as lf
from macromicro_sumo.evaluation.idm_fit import calibrate_idm
from macromicro_sumo.evaluation.leader_follower_section import run_leader_follower_for
from macromicro_sumo.policy.checkpoint import load_policy
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs

ROOT = Path(__file__).resolve().parents[1]
POLICIES = {"policy": "policy.pt", "micro_only": "policy_micro_only.pt"}
TRACE_COLUMNS = ["leader_speed_mps", "follower_speed_mps", "idm_follower_speed_mps", "gap_m"]


def main(args: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="ring_paper's run folder")
    p.add_argument("--ring", type=Path, default=ROOT / "scenarios" / "ring_paper.toml")
    p.add_argument("--section", type=Path, default=ROOT / "scenarios" / "ring_paper_section.toml")
    o = p.parse_args(args)
    torch.set_num_threads(1)  # as the evaluate stage
    ring, sec = load_scenario(o.ring), load_scenario(o.section)
    pol = o.run / "policy"
    agents = {n: load_policy(pol / f, ring) for n, f in POLICIES.items() if (pol / f).is_file()}
    gt = load_ground_truth(o.run / "ground_truth", ring)
    splits = split_runs(gt.runs, ring.generator.held_out_fraction, ring.seed)
    obs, acc = micro_pairs(ring, gt, np.concatenate([splits["train"], splits["val"]]))
    cal, _ = calibrate_idm(obs, acc, ring.fleet.length_m, ring.fleet.delta)

    t0 = time.perf_counter()
    tr_ring, sm_ring = leader_follower_tests(ring, agents, cal)
    t_ring = time.perf_counter() - t0

    net = scenario_inputs(sec).net_file
    section = read_section(net, list(sec.section.edges), sec.section.closed)
    followers = {n: lf.policy_follower(a) for n, a in agents.items()}
    cal_dict = {k: float(v) for k, v in cal.as_dict().items()}
    followers["idm_calibrated"] = lf.idm_follower(cal_dict, ring.fleet.length_m)
    d = ring.evaluation.lf_duration_s
    t0 = time.perf_counter()
    res = run_leader_follower_for(
        sec,
        section,
        net,
        followers,
        lf.mean_idm_params(sec),
        section.length_m / sec.fleet.n_vehicles,
        sec.fleet.length_m,
        ring.evaluation.lf_trials,
        ring.seed,
        lf.LeaderProfile(duration_s=d, hold_s=min(20.0, d / 3)),
    )
    t_sec = time.perf_counter() - t0
    print(res.message)
    if res.skipped:
        return 1
    a = lf.method_summary(sm_ring).set_index(["scenario", "method"])
    b = lf.method_summary(res.summary).set_index(["scenario", "method"])
    table = pd.DataFrame(
        {
            "ring_rmse_mps": a["mean_rmse_vs_idm_mps"],
            "section_rmse_mps": b["mean_rmse_vs_idm_mps"],
            "ring_min_gap_m": a["min_gap_m"],
            "section_min_gap_m": b["min_gap_m"],
            "ring_collisions": a["collisions"],
            "section_collisions": b["collisions"],
        }
    )
    print(table.round(4).to_string())
    if len(tr_ring) == len(res.traces):
        diff = {
            c: float(np.nanmax(np.abs(tr_ring[c].to_numpy() - res.traces[c].to_numpy())))
            for c in TRACE_COLUMNS
        }
        print("largest |ring - section| per column:", diff)
    else:
        print(f"trace lengths differ: ring {len(tr_ring)}, section {len(res.traces)} rows")
    print(f"wall time: ring {t_ring:.1f} s, section {t_sec:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
