"""Stage II's snapshot episodes hold every hidden vehicle to its vType's maxSpeed, as a
deployment does (``deploy.slots``): SUMO does not cap a speed command at it. A two-lane road
(limit 20 m/s) whose demand is mostly vans of maxSpeed 10 with some cars of maxSpeed 25;
real SUMO runs, hidden vehicles pushed at the largest acceleration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import dump_toml, line_net
from test_section_env import true_completion

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank, typical_vclass, typical_vtype
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

VAN_MAX_MPS, CAR_MAX_MPS, LIMIT_MPS = 10.0, 25.0, 20.0
HORIZON = 8


@pytest.fixture(scope="module")
def vans(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth, net) of the road: one run of 30 s warm-up + 60 s."""
    folder = tmp_path_factory.mktemp("section_max_speed")
    net = line_net(folder, (600.0, 1000.0), 2, LIMIT_MPS)
    routes = folder / "vans.rou.xml"
    routes.write_text(
        "<routes>\n"
        f'    <vType id="van" length="6" minGap="2.5" accel="2.6" decel="4.5" sigma="0" '
        f'maxSpeed="{VAN_MAX_MPS}" speedDev="0"/>\n'
        f'    <vType id="car" length="5" minGap="2.5" accel="2.6" decel="4.5" sigma="0" '
        f'maxSpeed="{CAR_MAX_MPS}" speedDev="0"/>\n'
        '    <flow id="v" type="van" begin="0" end="90" period="3" departSpeed="5" '
        'departLane="best"><route edges="A B"/></flow>\n'
        '    <flow id="c" type="car" begin="0" end="90" period="7" departSpeed="10" '
        'departLane="best"><route edges="A B"/></flow>\n'
        "</routes>\n"
    )
    table = {
        "name": "vans",
        "seed": 3,
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": ["A", "B"]},
        "instrumented": {"penetration": 0.5},
        "simulation": {"warmup_s": 30.0, "duration_s": 60.0, "n_runs": 1},
        "detectors": {"interval_s": 30.0},
        "bounds": {"accel_mps2": [-4.5, 2.6]},
        "policy": {"observation": "lookahead"},
    }
    path = folder / "vans.toml"
    path.write_text(dump_toml(table))
    sc = load_scenario(path)
    truth = load_section_truth(simulate_section(sc, folder / "gt", progress=False), sc)
    return sc, truth, net


def test_hidden_vehicles_never_exceed_their_vtypes_max_speed(vans) -> None:
    sc, truth, net = vans
    assert typical_vtype(truth) == "van"  # the generated vehicles' vType
    snaps = section_snapshots(truth, sc, truth.runs)
    bank = build_section_bank(sc, truth, snaps, true_completion, HORIZON, 0)
    cap = bank.vmax_mps
    # Generated slots: the typical vType's; observed ones: their recorded vType's.
    assert cap is not None and (cap[bank.hidden] == VAN_MAX_MPS).all()
    assert set(np.unique(cap[bank.observed])) == {VAN_MAX_MPS, CAR_MAX_MPS}
    assert np.isinf(cap[~bank.valid]).all()
    # They also start at most at it, where the completion had them faster (the true cars).
    _, _, speed, valid, generated = (np.asarray(x) for x in true_completion(snaps))
    assert (speed[valid & generated] > VAN_MAX_MPS + 1.0).any()
    assert (bank.speed0_mps[bank.hidden] <= VAN_MAX_MPS + 1e-9).all()
    push = lambda core, obs, rng: np.full(int(core.hidden.sum()), 2.6)  # noqa: E731
    top = {}
    for name, b in (("capped", bank), ("uncapped", dataclasses.replace(bank, vmax_mps=None))):
        for safety in ("none", "sumo"):
            core = SectionCore(
                sc, truth.section, b, net, seed=0, vclass=typical_vclass(truth), safety=safety
            )
            try:
                ro = rollout(core, push, HORIZON, 0)
            finally:
                core.close()
            hidden = np.broadcast_to(bank.hidden[:, None, :], ro.speed_mps.shape)
            assert np.isfinite(ro.speed_mps[hidden]).sum() > 100
            over = ro.speed_mps - cap[:, None, :]
            top[name, safety] = float(np.nanmax(np.where(hidden, over, np.nan)))
    # SUMO's speed after every step: never above the cap; without it, well above.
    assert top["capped", "none"] <= 1e-9 and top["capped", "sumo"] <= 1e-9, top
    assert top["uncapped", "none"] > 2.0 and top["uncapped", "sumo"] > 2.0, top
