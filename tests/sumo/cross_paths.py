"""A real SUMO run read and commanded two ways, for the tests of the compiled paths
(sumo/calls.c, sumo/libsumo_cxx.cpp): SUMO's game/cross with cars on four approaches; each
step's reads on the path under test against the same reads through ``reference`` (a
function that runs ``f()`` on the other path), and a second run of the same seed whose
commands go through ``reference``: both runs must move the cars alike, to the bit."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import sumo

from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
PAIRS = [("1si", "2o"), ("2si", "1o"), ("3si", "4o"), ("4si", "3o")]
Reference = Callable[[Callable[[], Any]], Any]


def cross_options(tmp_path: Path, cars: int = 40) -> SumoOptions:
    """game/cross, ``cars`` cars on four approaches, seed 3."""
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        + "".join(
            f'  <vehicle id="c{i:02d}" depart="{i // 4}" departSpeed="5">'
            f'<route edges="{" ".join(PAIRS[i % 4])}"/></vehicle>\n'
            for i in range(cars)
        )
        + "</routes>\n"
    )
    return SumoOptions(CROSS, (), 0.5, 3, route_files=(routes,), user_demand=True)


def same_both_ways(
    opts: SumoOptions,
    reference: Reference,
    check: Callable[[int, Any, list, list], None] | None = None,
    steps: int = 60,
) -> dict[str, int]:
    """Run ``opts`` twice for ``steps`` steps. In the first run, each step's vehicle states,
    lane states, leaders (100 m) and own speeds equal ``reference``'s to the bit (same
    dtypes and shapes), and ``check(step, states, lane_states, leaders)`` sees them; every
    car on an approach is commanded to 80% of its speed (+0.1). The second run sends the
    same commands through ``reference``; both runs' positions and speeds are equal to the
    bit. Returns counts over the first run: leaders found, cars commanded."""
    seen: dict[bool, list[np.ndarray]] = {}
    counts = {"leaders": 0, "commanded": 0}
    for first in (True, False):
        sim = Simulation(opts)
        got: list[np.ndarray] = []
        try:
            for step in range(steps):
                sim.step()
                if first:
                    st = sim.vehicle_states()
                    sim._states = None
                    want = reference(sim.vehicle_states)
                    assert st.ids == want.ids and st.lanes == want.lanes
                    for a, b in zip(
                        (st.pos_m, st.speed_mps, st.accel_mps2),
                        (want.pos_m, want.speed_mps, want.accel_mps2),
                        strict=True,
                    ):
                        assert a.dtype == b.dtype == np.float64 and a.shape == b.shape
                        assert a.tobytes() == b.tobytes()
                    ids = list(st.ids)
                    lanes = sim.lane_states(ids)
                    lanes_ref = reference(partial(sim.lane_states, ids))
                    assert lanes[0] == lanes_ref[0]
                    assert all(
                        x.tobytes() == y.tobytes()
                        for x, y in zip(lanes[1:], lanes_ref[1:], strict=True)
                    )
                    lead = sim.leaders(ids, 100.0)
                    assert lead == reference(partial(sim.leaders, ids, 100.0))
                    counts["leaders"] += sum(r[0] != "" for r in lead)
                    own = sim.own_speeds(ids)
                    assert own.tobytes() == reference(partial(sim.own_speeds, ids)).tobytes()
                    if check is not None:
                        check(step, st, lanes, lead)
                st = sim.vehicle_states()
                got += [st.pos_m.copy(), st.speed_mps.copy()]
                cmd = [
                    v
                    for v, la in zip(st.ids, st.lanes, strict=True)
                    if la.split("_")[0].endswith("si")
                ]
                speed = st.speed_mps[[st.index[v] for v in cmd]] * 0.8 + 0.1
                send = partial(sim.set_speeds, cmd, speed)
                send() if first else reference(send)
                counts["commanded"] += len(cmd) if first else 0
        finally:
            sim.close()
        seen[first] = got
    assert len(seen[True]) == len(seen[False]) == 2 * steps
    assert all(a.tobytes() == b.tobytes() for a, b in zip(seen[True], seen[False], strict=True))
    return counts
