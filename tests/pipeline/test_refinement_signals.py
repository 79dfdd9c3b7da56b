"""Joint refinement on a signalised section: the next-step scenes the generator is
fine-tuned on carry the red or yellow stop lines of their step, as every snapshot the
generator trains on does (real SUMO: game/cross's west approach, its static 90 s program)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import sumo
from section_files import section_scenario

from macromicro_sumo.data.section import section_snapshots, signal_stops
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank, with_future
from macromicro_sumo.pipeline.refinement import next_step_snapshots
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth, simulate_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"


def test_next_step_scenes_carry_the_stop_lines_of_their_step(tmp_path: Path) -> None:
    """One step after each episode's start the scene's stop lines are signals.csv's red or
    yellow ones at that step (before: none, so the fine-tune saw vehicles stand at a red
    light with nothing ahead of them). The truth's own scenes, an untrained policy."""
    path = section_scenario(
        tmp_path / "cross.toml",
        CROSS / "cross.net.xml",
        CROSS / "cross.rou.xml",
        ["1fi", "1si", "2o", "2fo"],
        seed=1,
        penetration=0.3,
        simulation={"step_length_s": 0.5, "warmup_s": 60.0, "duration_s": 120.0, "n_runs": 1},
        detectors={"interval_s": 60.0, "auto_spacing_m": 60.0},
        generator={"snapshot_every_s": 5.0},
        policy={"horizon": 2},
    )
    sc = load_scenario(path)
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    dt = sc.simulation.step_length_s
    snaps = section_snapshots(truth, sc, truth.runs)
    snaps = snaps.take(with_future(truth, snaps, sc.policy.horizon, dt))

    def true_scene(s):
        return s.lane, s.arc_m, s.speed_mps, s.valid, s.valid & ~s.observed

    bank = build_section_bank(sc, truth, snaps, true_scene, horizon=sc.policy.horizon)
    net_file = scenario_inputs(sc).net_file

    def make_core(b, seed: int) -> SectionCore:
        return SectionCore(sc, truth.section, b, net_file, seed=seed)

    agent = Agent(observation=sc.policy.observation)
    nxt = next_step_snapshots(sc, snaps, bank, make_core, agent, 1, truth.signals)
    assert len(nxt) > 10 and nxt.stop_lane is not None and nxt.stop_arc_m is not None
    want = signal_stops(truth.signals, nxt.run, nxt.time_s)
    assert want is not None
    np.testing.assert_array_equal(nxt.stop_lane, want[0])
    np.testing.assert_array_equal(nxt.stop_arc_m, want[1])
    red = np.isfinite(nxt.stop_arc_m).any(axis=1)
    assert red.any() and not red.all()  # scenes at red and at green
