"""signals.csv gives each lane its own link's state (``truth.signals.section_signal_links``).

SUMO's game/cross, its west approach 1si as the section's signalised edge: lane 0 turns
right (link 6 onto 3o), lane 1 goes through (link 7 onto 2o, the section's next edge),
lane 2 turns left (link 8 onto 4o). The static program gives the left turn a protected
6 s phase (phase 2: through red, left green) and a yellow after it while the through
link is red. Before, every lane of 1si got link 7's state: the left-turn lane showed red
in its own green phase, and the micro pairs and the generator's snapshots took a
standing leader at its line then.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo
from section_files import section_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import stop_lines_at
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import STOP_STATES
from macromicro_sumo.truth.section import load_section_truth

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross"


@pytest.fixture(scope="module")
def cross(tmp_path_factory: pytest.TempPathFactory):
    """(scenario, ground truth) of game/cross's west approach and exit: one run, 60 s of
    warm-up and 120 s recorded (t = 60.5-180 s: every phase of the 90 s program)."""
    folder = tmp_path_factory.mktemp("cross_lanes")
    net, routes = CROSS / "cross.net.xml", CROSS / "cross.rou.xml"
    path = section_scenario(
        folder / "cross.toml",
        net,
        routes,
        ["1fi", "1si", "2o", "2fo"],
        seed=1,
        penetration=0.3,
        simulation={"step_length_s": 0.5, "warmup_s": 60.0, "duration_s": 120.0, "n_runs": 1},
        detectors={"interval_s": 60.0, "auto_spacing_m": 60.0},
        network={"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
    )
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    sc = load_scenario(path)
    return sc, load_section_truth(folder / "gt", sc)


def sumo_states(sc, times_s: np.ndarray):
    """SUMO's own view at each recorded time, in a run of its own (the program is static,
    so the lights follow the clock): {time: ({1si lane: its link's state letter},
    {1si lane: whether a vehicle on it has a red or yellow line ahead on its own route
    (``getNextTLS``), for each vehicle there})}."""
    inputs = scenario_inputs(sc)
    opts = SumoOptions(
        inputs.net_file,
        inputs.additional_files,
        sc.simulation.step_length_s,
        sc.seed,
        route_files=inputs.route_files,
        user_demand=True,
    )
    sim = Simulation(opts)
    out = {}
    try:
        own = {int(src.rsplit("_", 1)[1]): i for _, i, src, _, _ in sim.signal_links()
               if src.startswith("1si_")}  # fmt: skip
        assert sorted(own) == [0, 1, 2] and len(set(own.values())) == 3
        want = {round(float(t), 6) for t in times_s}
        step = 0
        while len(out) < len(want):
            sim.step()
            step += 1
            t = round(step * sc.simulation.step_length_s, 6)
            if t not in want:
                continue
            state = sim.signal_states(["0"])[0][3]
            st = sim.vehicle_states()
            seen: dict[int, list[bool]] = {}
            for vid, lane in zip(st.ids, st.lanes, strict=True):
                if lane.startswith("1si_"):
                    red = np.isfinite(sim.stop_line_m(vid))
                    seen.setdefault(int(lane.rsplit("_", 1)[1]), []).append(bool(red))
            out[t] = ({ln: state[i] for ln, i in own.items()}, seen)
    finally:
        sim.close()
    return out


def test_each_lane_records_its_own_links_state(cross) -> None:
    """At every recorded step the state signals.csv gives each lane of 1si (the left-turn
    lane above all) is SUMO's own state of that lane's link, and a vehicle on it has a red
    or yellow line ahead in SUMO exactly when its lane's recorded letter is red or yellow.
    The left-turn lane's green phase is in the record (before: red then, the through
    link's)."""
    sc, truth = cross
    sig = truth.signals
    times = np.unique(sig["time_s"].to_numpy())
    assert len(times) == 240
    sumo_view = sumo_states(sc, times)
    rec = {(round(float(t), 6), int(ln)): s
           for t, ln, s in sig[["time_s", "lane_index", "state"]].itertuples(False)}  # fmt: skip
    assert len(rec) == len(sig) == 3 * len(times)  # one link per lane
    vehicles = 0
    for t, (states, seen) in sumo_view.items():
        for ln in (0, 1, 2):
            assert rec[(t, ln)] == states[ln], (t, ln)
        for ln, reds in seen.items():
            vehicles += len(reds)
            assert all(r == (rec[(t, ln)] in STOP_STATES) for r in reds), (t, ln, reds)
    assert vehicles > 100
    left_green = [t for t, (s, _) in sumo_view.items() if s[2] in "Gg" and s[1] in STOP_STATES]
    assert len(left_green) >= 12  # the 6 s protected phase at least
    # What the micro pairs and the generator's snapshots read: red lines on the right-turn
    # and through lanes at 1si's end then, none on the left-turn lane.
    stops = stop_lines_at(truth, 0, np.array(left_green))
    end = float(truth.section.offsets_m[1] + truth.section.lengths_m[1])
    for t in left_green:
        lane, arc = stops[round(t, 6)]
        assert sorted(lane.tolist()) == [0, 1] and np.allclose(arc, end), t
