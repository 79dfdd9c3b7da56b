"""``sumo.simulation.Simulation.blocked_changes`` on a real net (libsumo, LC2013): the
change a vehicle's route needs, urgent and blocked, gives its own speed and the followers
blocking it; a change it wants without urgency, or for speed, or none, gives NaN.

A (1,500 m, two lanes, 15 m/s) -> B (one lane, reached from A's lane 1 only). A stream on
lane 1 every 1.0 s until 100 s (``lcCooperative`` 0: nobody opens a gap) and "m" on lane 0
at 10 s, which must change left to reach B ("n" too, at 170 s once the stream is gone,
with TraCI's lane-change mode 0: it never changes, urgent and mostly unblocked). Measured
(SUMO 1.28, seed 5): LC2013 first finds the left lane blocked with no wish to change,
then wants it for its route without urgency (and for speed), then urgently from some 360 m
before the end, where it brakes and stands before the lane end (1,488.5 m) until the
stream has passed. A copy of ``blocked_changes`` without the urgency test, or without the
blocked one, fails here.
"""

from __future__ import annotations

from pathlib import Path

import libsumo
import numpy as np
from conftest import netconvert

from macromicro_sumo.sumo.simulation import Simulation, SumoOptions

C = libsumo.constants
END_M = 1500.0


def _run(folder: Path) -> tuple[list[dict], list[tuple]]:
    """Per step with "m" on A: its state and what ``blocked_changes`` says of it and of a
    stream vehicle; per step with "n" on A: (its state, what ``blocked_changes`` says)."""
    nodes = (
        f'<node id="n0" x="0" y="0"/><node id="j" x="{END_M:g}" y="0"/>'
        f'<node id="n2" x="{END_M + 200:g}" y="0"/>'
    )
    edges = (
        '<edge id="A" from="n0" to="j" numLanes="2" speed="15"/>'
        '<edge id="B" from="j" to="n2" numLanes="1" speed="15"/>'
    )
    net = netconvert(folder, nodes, edges, '<connection from="A" to="B" fromLane="1" toLane="0"/>')
    routes = folder / "r.rou.xml"
    routes.write_text(
        '<routes>\n    <vType id="car" length="5" minGap="2.5" lcCooperative="0" sigma="0"/>\n'
        '    <route id="r" edges="A B"/>\n'
        '    <flow id="s" type="car" route="r" begin="0" end="100" period="1.0" departLane="1" '
        'departSpeed="max"/>\n'
        '    <vehicle id="m" type="car" route="r" depart="10" departLane="0" departSpeed="max"/>\n'
        '    <vehicle id="n" type="car" route="r" depart="170" departLane="0" departSpeed="max"/>\n'
        "</routes>\n"
    )
    sim = Simulation(SumoOptions(net, (), 0.5, 5, route_files=(routes,), user_demand=True))
    rows, unforced, seen_b = [], [], False
    try:
        for _ in range(720):
            sim.step()
            ids = libsumo.vehicle.getIDList()
            if "n" in ids and libsumo.vehicle.getLaneID("n") == "A_0":
                libsumo.vehicle.setLaneChangeMode("n", 0)
                unforced.append(
                    (libsumo.vehicle.getLaneChangeState("n", 1)[0], sim.blocked_changes(["n"], [1]))
                )
            if "m" not in ids:
                continue
            lane = libsumo.vehicle.getLaneID("m")
            seen_b |= lane == "B_0"
            if lane != "A_0":
                continue
            left = sim.blocked_changes(["m"], [1])
            right = sim.blocked_changes(["m"], [-1])
            stream = [v for v in libsumo.lane.getLastStepVehicleIDs("A_1")][:1]
            rows.append(
                {
                    "pos": libsumo.vehicle.getLanePosition("m"),
                    "speed": libsumo.vehicle.getSpeedWithoutTraCI("m"),
                    "state": libsumo.vehicle.getLaneChangeState("m", 1)[0],
                    "blockers": {
                        f: libsumo.vehicle.getSpeedWithoutTraCI(f)
                        for f, _ in libsumo.vehicle.getLeftFollowers("m", True)
                    },
                    "blocker_lanes": {
                        libsumo.vehicle.getLaneID(f)
                        for f, _ in libsumo.vehicle.getLeftFollowers("m", True)
                    },
                    "left": left,
                    "right": right,
                    "stream": sim.blocked_changes(stream, [1] * len(stream)),
                }
            )
    finally:
        sim.close()
    assert seen_b, "m never reached B: the case did not run as measured"
    return rows, unforced


def test_an_urgent_blocked_route_change_and_its_blockers(tmp_path: Path) -> None:
    rows, unforced = _run(tmp_path)
    urgent = [r for r in rows if np.isfinite(r["left"][0][0])]
    # The urgent phase: its own speed, and the lane-1 followers that block it at theirs
    assert len(urgent) > 20
    assert min(r["pos"] for r in urgent) > END_M - 400.0  # measured: 359 m before the end
    for r in urgent:
        own, back = r["left"]
        assert own.shape == (1,) and own[0] == r["speed"]
        assert back == r["blockers"]
        assert r["blocker_lanes"] <= {"A_1"}
        assert r["state"] & C.LCA_LEFT and r["state"] & C.LCA_URGENT
        assert r["state"] & C.LCA_BLOCKED_LEFT
    assert sum(bool(r["left"][1]) for r in urgent) > 10  # blocked by a follower, not only ahead
    # ... down to standing at the lane end, still blocked
    assert any(r["speed"] == 0.0 and r["pos"] > END_M - 20.0 for r in urgent)  # 1488.5 m
    # Blocked while the change is not urgent: NaN and no blockers, whatever the wish
    calm = [r for r in rows if not np.isfinite(r["left"][0][0])]
    assert all(r["left"][1] == {} for r in calm)
    blocked = [r for r in calm if r["state"] & C.LCA_BLOCKED_LEFT]
    strategic = [r for r in blocked if r["state"] & C.LCA_STRATEGIC]
    speed_gain = [r for r in blocked if r["state"] & C.LCA_SPEEDGAIN]
    no_wish = [r for r in blocked if not r["state"] & C.LCA_WANTS_LANECHANGE]
    assert strategic and speed_gain and no_wish, (len(strategic), len(speed_gain), len(no_wish))
    assert all(not r["state"] & C.LCA_URGENT for r in strategic)
    # with blocking followers beside it in that phase, none reported
    assert any(r["blockers"] for r in strategic + speed_gain)
    assert max(r["pos"] for r in strategic + speed_gain) < min(r["pos"] for r in urgent)
    # No lane to the right: nothing; a stream car on its route's lane: nothing
    for r in rows:
        assert np.isnan(r["right"][0]).all() and r["right"][1] == {}
        own, back = r["stream"]
        assert np.isnan(own).all() and back == {}
    # Urgent, but nothing blocks it ("n", told by TraCI not to change): nothing
    free = [got for state, got in unforced if state & C.LCA_URGENT and not state & C.LCA_BLOCKED]
    assert len(free) > 100  # measured: 221 of its 230 urgent steps
    assert all(np.isnan(own).all() and back == {} for own, back in free)
