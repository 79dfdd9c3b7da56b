"""Stage II rollouts on a small multi-lane section with a merge: no collisions.

The merge of ``tests/road/test_section_leaders.py``'s net (an on-ramp lane added on the
right, which ends; the through lanes' indices shift by one): a dense scene, hidden vehicles
driven by an aggressive constant acceleration, observed ones replaying their records.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "env"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "road"))

from test_section_env import section_scenario, synthetic_bank  # noqa: E402
from test_section_leaders import EDGES, build_merge_net  # noqa: E402

from macromicro_sumo.env.rollout import rollout  # noqa: E402
from macromicro_sumo.env.section import SectionCore  # noqa: E402
from macromicro_sumo.road.section import read_section  # noqa: E402


def test_dense_merge_rollout_has_no_collision(tmp_path):
    net = build_merge_net(tmp_path)
    section = read_section(net, EDGES, closed=False)
    sc = section_scenario(tmp_path, net, EDGES, False)
    b0 = float(section.offsets_m[1])
    # a's two lanes 20 m apart, the ramp lane (b_0) and b's through lanes, all at 25 m/s
    lanes = [0, 1, 0, 1, 0, 1, 0, 1, 2, 1, 2, 0, 0]
    arcs = [150, 160, 190, 200, 230, 240, 270, 280, 0, b0 + 20, b0 + 30, b0 + 40, b0 + 90]
    arcs = [float(a) if a else b0 + 60.0 for a in arcs]
    hidden = [i % 3 != 0 for i in range(len(arcs))]
    bank = synthetic_bank(lanes, arcs, [25.0] * len(arcs), hidden, horizon=20)
    push = lambda core, obs, rng: np.full(int(core.hidden.sum()), 2.0)  # noqa: E731
    core = SectionCore(sc, section, bank, net, seed=0)  # the default safety layer
    try:
        ro = rollout(core, push, 20, 0)
        assert ro.collisions == 0 and ro.errors == 0
        assert np.isfinite(ro.speed_mps[0, -1]).sum() >= 5  # the episode ran to its end
        assert core.counts["safety_capped"] > 0  # ... because the layer acted
    finally:
        core.close()
