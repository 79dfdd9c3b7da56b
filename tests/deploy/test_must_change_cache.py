"""``MergeYield.must_change`` keeps its last vehicles not driven (``_last_others``) and
answers from them while the same vehicles are on the same lanes and none is due again in
the lane-end cache: the same answers, cache entries and SUMO calls as asking every step
(the merge of ``deploy_nets.merge_net``, 20% instrumented, real SUMO)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from deploy_nets import idm_agent, merge_scenario

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.policy_batch import policy_batch
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section


class Recording(SectionSpeedDriver):
    """Records per ``must_change`` call its answer, ``others`` and the lane-end cache's
    entries of those (lane code, value, step due again, offset), and whether it answered
    from its last vehicles; ``fresh``: forgets them before every call (asks every step)."""

    fresh = False
    calls: list[tuple]
    reused: int = 0

    def must_change(self, sim, vids, slots, st):  # type: ignore[no-untyped-def]
        if self.fresh:
            self._last_others = None
        before = self._last_others
        out = super().must_change(sim, vids, slots, st)
        self.reused += before is not None and self._last_others is before
        c = self.slots.lane_end
        at = self.slots.slots(sorted(self.others))
        entries = list(zip(c.lane[at].tolist(), c.value[at].tolist(), c.again[at].tolist(),
                           c.offset[at].tolist(), strict=True))  # fmt: skip
        self.calls.append((self.steps, out, sorted(self.others), entries))
        return out


def _run(sc, fresh: bool) -> Recording:
    inputs, section, _ = load_section(sc)
    drv = Recording(sc, section, 0, policy_batch(idm_agent("lookahead", 30.0)), "sumo")
    drv.fresh, drv.calls = fresh, []
    opts = SumoOptions(
        inputs.net_file, (), sc.simulation.step_length_s, sc.seed,
        route_files=inputs.route_files, user_demand=True,
    )  # fmt: skip
    sim = Simulation(opts)
    try:
        for _ in range(int(sc.simulation.duration_s / sc.simulation.step_length_s)):
            drv.before_step(sim)
            sim.step()
    finally:
        sim.close()
    return drv


def test_must_change_from_its_last_vehicles_is_asking_every_step(tmp_path: Path) -> None:
    path = merge_scenario(
        tmp_path,
        {"warmup_s": 0.0, "duration_s": 90.0, "n_runs": 1},
        policy={"observation": "lookahead"},
        deploy={"merge_reach": "occupation"},
    )
    base = load_scenario(path)
    sc = dataclasses.replace(base, deploy=dataclasses.replace(base.deploy, merge="sumo"))
    kept, asked = _run(sc, fresh=False), _run(sc, fresh=True)
    assert kept.yield_all and len(kept.calls) > 100
    # Vehicles not driven on the section, some that must change lane, in most calls.
    assert sum(bool(c[2]) for c in kept.calls) > 50
    assert any(set(c[1]) & set(c[2]) for c in kept.calls)
    # Answered from the last vehicles often, and never when asked every step.
    assert kept.reused > 20 and asked.reused == 0, (kept.reused, asked.reused)
    assert kept.calls == asked.calls
