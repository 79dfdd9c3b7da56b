"""Signals in Stage II: the truth records them, an episode starts with them as recorded.

SUMO's game/cross (one junction, a static 90 s program) with its west approach as the
section. A Stage II env runs its own SUMO clock: before signals.csv its lights showed
whatever that clock said, not the truth's at the snapshot (a car the truth saw drive
through a green light met a red one and stopped in one step, and the car behind ran
into it: 12 of 84 evaluation episodes on game/cross).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sumo
from section_files import section_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import recorded_snapshots
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import build_section_bank
from macromicro_sumo.evaluation.micro_data import micro_pairs
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.sumo.simulation import Simulation, SumoOptions
from macromicro_sumo.truth.section import load_section_truth

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"


def cross_truth_in(folder: Path, duration_s: float, n_runs: int, *additional: Path):
    """(scenario, ground truth) of game/cross's west approach and exit, simulated into
    ``folder`` with the user's ``additional`` files (a signal program)."""
    net, routes = CROSS / "cross.net.xml", CROSS / "cross.rou.xml"
    path = section_scenario(
        folder / "cross.toml",
        net,
        routes,
        ["1fi", "1si", "2o", "2fo"],
        seed=1,
        penetration=0.3,
        simulation={
            "step_length_s": 0.5,
            "warmup_s": duration_s / 2,
            "duration_s": duration_s,
            "n_runs": n_runs,
        },
        detectors={"interval_s": duration_s / 2, "auto_spacing_m": 60.0},
        generator={"snapshot_every_s": 5.0},
        network={
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(routes)],
            "additional_files": [str(a) for a in additional],
        },
    )
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    sc = load_scenario(path)
    return sc, load_section_truth(folder / "gt", sc)


@pytest.fixture(scope="module")
def cross_truth(tmp_path_factory: pytest.TempPathFactory):
    return cross_truth_in(tmp_path_factory.mktemp("cross"), 120.0, 2)


def recorded_signals(truth) -> pd.DataFrame:
    """signals.csv's one row per (run, time) (the one signal's state), indexed by them."""
    want = truth.signals.drop_duplicates(["run", "time_s"]).set_index(["run", "time_s"])
    want.index = want.index.set_levels(want.index.levels[1].to_numpy().round(6), level=1)
    return want


def episode_signals(sc, truth, snaps, horizon: int, every: int = 1) -> list[tuple]:
    """(run, time, program, phase, seconds left) of signal "0" at every step of every
    ``every``-th Stage II episode on the truth's own scenes (driven at 0 m/s^2)."""

    def true_scene(s):
        return s.lane, s.arc_m, s.speed_mps, s.valid, s.valid & ~s.observed

    bank = build_section_bank(sc, truth, snaps, true_scene, horizon=horizon)
    core = SectionCore(sc, truth.section, bank, scenario_inputs(sc).net_file, seed=1)
    out = []
    try:
        for ep in range(0, len(bank), every):
            core.reset(ep)
            for k in range(horizon + 1):
                if k:
                    core.step(np.zeros(int(core.hidden.sum())))
                t = round(float(bank.time_s[ep]) + k * core.dt, 6)
                program, phase, left, _ = core.sim.signal_states(["0"])[0]
                out.append((int(bank.run[ep]), t, program, phase, left))
    finally:
        core.close()
    return out


def test_truth_records_the_signals_on_the_section(cross_truth) -> None:
    """Every recorded step, a row for each of 1si's three lanes at 1si's end, each lane
    its own link's state (truth.signals.section_signal_links; tests/truth/test_signal_lanes.py
    checks each letter against SUMO); the through lane's follow the program (green 33 s of
    90, yellow 3, red)."""
    sc, truth = cross_truth
    sig = truth.signals
    steps = int(round(sc.simulation.duration_s / sc.simulation.step_length_s))
    assert len(sig) == 2 * steps * 3
    sec = truth.section
    end = float(sec.offsets_m[1] + sec.lengths_m[1])
    assert sorted(sig["lane_index"].unique()) == [0, 1, 2]
    np.testing.assert_allclose(sig["arc_m"].unique(), [end])
    one = sig[(sig["run"] == 0) & (sig["lane_index"] == 1)]
    assert set(one["state"]) == {"G", "y", "r"}
    # t = 60-180 s: green 90-123 s (33 s of the program's phase 0), yellow 123-126 s
    assert (one["state"] == "G").mean() == pytest.approx(33 / 120)
    assert (one["state"] == "y").mean() == pytest.approx(3 / 120)


def test_episodes_show_the_truths_signals_at_every_step(cross_truth) -> None:
    """Reset at a snapshot puts the signal where the truth had it (phase and seconds left),
    and the program runs on from there as in the truth, over the whole horizon; the
    snapshots carry the red or yellow stop lines (standing leaders for the generator)."""
    sc, truth = cross_truth
    snaps = recorded_snapshots(truth, sc, truth.runs)
    assert snaps.stop_arc_m is not None
    red = truth.signals.query("state in ['r', 'y']").drop_duplicates(["run", "time_s"])
    keys = set(zip(red["run"], red["time_s"].round(6), strict=True))
    stopped = np.isfinite(snaps.stop_arc_m).any(axis=1)
    np.testing.assert_array_equal(
        stopped, [(r, round(t, 6)) in keys for r, t in zip(snaps.run, snaps.time_s, strict=True)]
    )
    assert stopped.any() and not stopped.all()

    states = episode_signals(sc, truth, snaps, horizon=6, every=3)
    want = recorded_signals(truth)
    assert len(states) > 20
    for run, t, program, phase, left in states:
        rec = want.loc[(run, t)]
        assert (program, phase) == (str(rec["program"]), rec["phase"])
        assert left == pytest.approx(rec["left_s"], abs=1e-6)


def test_a_program_the_env_lacks_leaves_the_signal_as_it_is(cross_truth) -> None:
    """A recorded program the env's run does not have (a user's additional file defines it;
    the env loads only the net) is no error: that signal keeps the env's own state."""
    sc, truth = cross_truth
    sim = Simulation(SumoOptions(scenario_inputs(sc).net_file, (), 0.5, 1))
    try:
        before = sim.signal_states(["0"])[0]
        sim.set_signal_states([("0", "user_program", 4, 7.0), ("no_such_signal", "0", 0, 1.0)])
        assert sim.signal_states(["0"])[0] == before
        sim.set_signal_states([("0", "0", 4, 7.0)])
        assert sim.signal_states(["0"])[0][1:3] == (4, 7.0)
    finally:
        sim.close()


def test_episodes_run_the_users_own_signal_program(tmp_path: Path) -> None:
    """A program from the user's additional files (not the net's): the truth records it, and
    a Stage II episode shows it, phase and seconds left, at every step. Before the env
    loaded the user's programs, its run lacked the program and kept the net's own."""
    add = tmp_path / "user.tls.add.xml"
    add.write_text(
        '<additional><tlLogic id="0" type="static" programID="user" offset="0">'
        '<phase duration="7" state="GGGGGGGGGGGG"/><phase duration="2" state="yyyyyyyyyyyy"/>'
        '<phase duration="11" state="rrrrrrrrrrrr"/></tlLogic></additional>'
    )
    sc, truth = cross_truth_in(tmp_path, 80.0, 1, add)
    assert set(truth.signals["program"].astype(str)) == {"user"}
    snaps = recorded_snapshots(truth, sc, truth.runs)

    states = episode_signals(sc, truth, snaps, horizon=4)
    want = recorded_signals(truth)
    assert len(states) > 20
    for run, t, program, phase, left in states:
        rec = want.loc[(run, t)]
        assert program == "user"
        assert (phase, left) == pytest.approx((rec["phase"], rec["left_s"]), abs=1e-6)


def test_driven_vehicles_see_their_turning_lanes_end(cross_truth) -> None:
    """A hidden vehicle drives the section's route: on 1si's turning lanes (0, 2) with no
    vehicle ahead on its lane, the lane's end is its standing leader at every step, on
    green too (before: a free road, 250 m), at the distance plus minGap 2.5 m and its own
    length (``road.leaders.standing_spacing_m``: SUMO stops at a lane's end); a replayed observed vehicle there keeps its
    own route's free road where the light is green."""
    sc, truth = cross_truth
    snaps = recorded_snapshots(truth, sc, truth.runs)

    def true_scene(s):
        return s.lane, s.arc_m, s.speed_mps, s.valid, s.valid & ~s.observed

    bank = build_section_bank(sc, truth, snaps, true_scene, horizon=4)
    core = SectionCore(sc, truth.section, bank, scenario_inputs(sc).net_file, seed=1)
    sec = truth.section
    end = float(sec.offsets_m[1] + sec.lengths_m[1])
    seen = {True: [], False: []}  # hidden: spacing - (distance to the end + 2.5 + own length)
    try:
        for ep in range(0, len(bank), 2):
            core.reset(ep)
            for k in range(5):
                if k:
                    core.step(np.zeros(int(core.hidden.sum())))
                on = np.flatnonzero(core.active)
                turning = np.isin(core.lane[on], [0, 2]) & (core.arc[on] > sec.offsets_m[1])
                for i in on[turning & (core.arc[on] < end)]:
                    same = on[(core.lane[on] == core.lane[i]) & (core.arc[on] > core.arc[i])]
                    green = not np.isfinite(core.sim.stop_lines_m([core.ids[i]])[0])
                    if not same.size and green:
                        own = float(core.bank.length_m[core.episode, i])
                        gap = core._obs[i, 2] - (end - core.arc[i] + 2.5 + own)
                        seen[bool(core.hidden[i])].append(gap)
    finally:
        core.close()
    assert len(seen[True]) > 5
    np.testing.assert_allclose(seen[True], 0.0, atol=1e-6)
    assert seen[False] and all(g > 100.0 for g in seen[False])


def test_micro_pairs_at_a_red_light_see_the_stop_line(cross_truth) -> None:
    """The observed vehicles' (observation, action) pairs (``micro_pairs``: idm_calibrated's
    fit, the prior's) see a red or yellow stop line as the envs show it: a standing leader
    at the distance plus the own length. Before, a vehicle standing at the line observed a
    free road (spacing 250 m), and the fit read its standing as a choice of its own."""
    sc, truth = cross_truth
    obs, _ = micro_pairs(sc, truth, truth.runs)
    standing = obs[:, 0] <= 0.1
    free = obs[:, 2] >= NO_LEADER_GAP_M
    assert standing.sum() > 20
    at_line = standing & (obs[:, 2] < 5.0 + 3.0)  # the own 5 m and at most 3 m to go
    assert at_line.sum() > 10
    assert (standing & free).sum() < 0.1 * at_line.sum()
