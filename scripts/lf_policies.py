"""Leader-follower tests (paper Fig. 3) of trained policies as the section evaluation runs them.

For each ``--policy`` folder (``policy/`` of a ``macromicro run``): the selected policy
(``policy.pt``) and, with ``--last``, the last PPO update (``state_dict`` of
``policy_mix_checkpoint.pt``; the selected one is the update that ``checkpoint_selection``
kept), each as the stochastic follower the evaluation uses and by its mean action (no action
noise: what the training alone does). The test is the evaluation's
(``leader_follower_section.run_leader_follower_for`` with the fleet's mid-range IDM as
reference, the leader profile of ``evaluation.lf_duration_s``, ``evaluation.lf_trials``
trials) at the scenario's seed or at each of ``--eval-seeds``.

    python scripts/lf_policies.py --scenario scenarios/ring_paper_section.toml \
        --policy runs/ring_paper/policy [--policy ...] [--last] [--eval-seeds 2024 2025]

Prints mean RMSE against the reference per policy, follower and scenario; ``--out`` writes
them as CSV.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pandas as pd
import torch

from macromicro_sumo.evaluation import leader_follower as lf
from macromicro_sumo.evaluation.leader_follower_section import run_leader_follower_for
from macromicro_sumo.policy.checkpoint import load_policy, read_checkpoint
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs


def followers(folder: Path, sc, last: bool) -> dict[str, lf.Follower]:
    """The selected policy (and the last update), stochastic and by their mean action. The
    scenario takes the checkpoint's ``policy.prior`` (a policy of another prior than the
    scenario's: a residual variant measured beside the scenario's own)."""
    prior = read_checkpoint(folder / "policy.pt").get("prior", "none")
    sc = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, prior=prior))
    agents = {"selected": load_policy(folder / "policy.pt", sc)}
    if last:
        agent = load_policy(folder / "policy.pt", sc)
        ckpt = torch.load(folder / "policy_mix_checkpoint.pt", weights_only=True)
        agent.load_state_dict(ckpt["state_dict"])
        agents[f"last_{ckpt['update']}"] = agent.eval()
    out: dict[str, lf.Follower] = {}
    for name, agent in agents.items():
        out[name] = lf.policy_follower(agent)
        out[f"{name}_mean"] = lf.policy_follower(agent, stochastic=False)
    return out


def main(args: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", type=Path, required=True, help="a section scenario with [fleet]")
    p.add_argument("--policy", type=Path, action="append", required=True, help="policy folder")
    p.add_argument("--last", action="store_true", help="also the last PPO update")
    p.add_argument("--eval-seeds", type=int, nargs="*", default=[], help="default: scenario.seed")
    p.add_argument("--out", type=Path, help="CSV of the table")
    o = p.parse_args(args)
    torch.set_num_threads(1)  # as the evaluate stage
    sc = load_scenario(o.scenario)
    net = scenario_inputs(sc).net_file
    section = read_section(net, list(sc.section.edges), sc.section.closed)
    d = sc.evaluation.lf_duration_s
    profile = lf.LeaderProfile(duration_s=d, hold_s=min(20.0, d / 3))
    rows = []
    for folder in o.policy:
        fol = followers(folder, sc, o.last)
        for seed in o.eval_seeds or [sc.seed]:
            res = run_leader_follower_for(
                dataclasses.replace(sc, seed=seed),
                section,
                net,
                fol,
                lf.mean_idm_params(sc),
                section.length_m / sc.fleet.n_vehicles,
                sc.fleet.length_m,
                sc.evaluation.lf_trials,
                seed,
                profile,
            )
            if res.skipped:
                print(res.message)
                return 1
            s = lf.method_summary(res.summary)
            rows.append(s[s["method"] != lf.IDM_METHOD].assign(policy=str(folder), eval_seed=seed))
    table = pd.concat(rows).pivot_table(
        index=["policy", "method", "eval_seed"],
        columns="scenario",
        values="mean_rmse_vs_idm_mps",
        sort=False,
    )
    print(table.round(3).to_string())
    if o.out is not None:
        table.to_csv(o.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
