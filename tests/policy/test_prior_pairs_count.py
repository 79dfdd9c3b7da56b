"""The policy manifest's ``prior.pairs`` counts the pairs the prior was fitted on: the IDM
prior takes only those with no lower limit ahead (``road.physics.no_lower_limit_ahead``),
and the count says so (real SUMO: a road whose limit drops from 30 to 15 m/s)."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from section_files import routes_file, section_scenario

sys.path.insert(0, str(Path(__file__).parents[1] / "deploy"))
from deploy_nets import netconvert  # noqa: E402

from macromicro_sumo.evaluation.idm_fit import MIN_PRIOR_PAIRS  # noqa: E402
from macromicro_sumo.evaluation.section import micro_pairs  # noqa: E402
from macromicro_sumo.pipeline.build import fit_residual_prior  # noqa: E402
from macromicro_sumo.road.physics import no_lower_limit_ahead  # noqa: E402
from macromicro_sumo.scenario.load import load_scenario  # noqa: E402
from macromicro_sumo.truth.section import load_section_truth, simulate_section  # noqa: E402


def test_the_idm_priors_pair_count_is_its_own_subset(tmp_path: Path):
    net = netconvert(
        tmp_path,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="800" y="0"/>\n<node id="c" x="1400" y="0"/>',
        '<edge id="A" from="a" to="b" numLanes="1" speed="30"/>\n'
        '<edge id="B" from="b" to="c" numLanes="1" speed="15"/>',
    )
    routes = routes_file(
        tmp_path / "r.rou.xml",
        flows=['<flow id="f" route="r" begin="0" end="3600" period="4" departSpeed="max"/>'],
        routes=['<route id="r" edges="A B"/>'],
    )
    section_scenario(
        tmp_path / "drop.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=1.0,
        simulation={"warmup_s": 60.0, "duration_s": 60.0, "n_runs": 1},
        detectors={"interval_s": 30.0, "auto_spacing_m": 500.0},
        policy={"prior": "idm", "observation": "lookahead"},
    )
    sc = load_scenario(tmp_path / "drop.toml")
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    obs, _ = micro_pairs(sc, truth, truth.runs)
    own = int(no_lower_limit_ahead(obs).sum())
    assert MIN_PRIOR_PAIRS <= own < len(obs)  # some pairs see the drop ahead, enough do not
    _, extra, (all_obs, _, _) = fit_residual_prior(sc, truth, truth.runs)
    assert extra["prior"]["pairs"] == own and len(all_obs) == len(obs)
    # The other priors are fitted on every pair.
    gipps = replace(sc, policy=replace(sc.policy, prior="gipps"))
    assert fit_residual_prior(gipps, truth, truth.runs)[1]["prior"]["pairs"] == len(obs)
    assert np.isfinite(extra["prior"]["fit_rmse_mps2"])
