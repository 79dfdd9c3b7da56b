"""sumo/libsumo_cxx.cpp (``sumo.direct``): a step's per-vehicle libsumo calls on libsumo's C++
functions give what the SWIG wrappers give, to the bit, on a real SUMO run; whatever it
cannot take (an ID or output of another form, an unknown vehicle) goes back to the
wrappers, which answer or raise as before; the environment switch turns it off."""

from __future__ import annotations

import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import libsumo
import numpy as np
import pytest
import sumo

from macromicro_sumo.sumo import direct
from macromicro_sumo.sumo.options import SumoOptions
from macromicro_sumo.sumo.simulation import Simulation

lib = pytest.importorskip(
    "macromicro_sumo.sumo.libsumo_cxx", reason="sumo/libsumo_cxx.cpp not built"
)
OFF = os.environ.get("MACROMICRO_SUMO_DIRECT") == "0"  # switched off for this process

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
PAIRS = [("1si", "2o"), ("2si", "1o"), ("3si", "4o"), ("4si", "3o")]


@pytest.fixture
def wrappers(monkeypatch: pytest.MonkeyPatch):
    """A function that runs ``f()`` with sumo/libsumo_cxx.cpp switched off (the wrappers)."""

    def run(f):
        with monkeypatch.context() as m:
            m.setattr(direct, "lib", None)
            return f()

    return run


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


@pytest.mark.skipif(OFF, reason="MACROMICRO_SUMO_DIRECT=0")
def test_a_runs_reads_and_commands_are_the_wrappers_to_the_bit(tmp_path: Path, wrappers) -> None:
    """Each step's states, lane states, leaders and own speeds read both ways are equal to
    the bit (same types, dtypes and shapes); the same speed commands sent both ways move
    the cars alike (two runs of the same seed)."""
    assert lib.available() and direct.lib is lib
    opts = cross_options(tmp_path)
    seen: dict[bool, list[np.ndarray]] = {}
    for on in (True, False):
        sim = Simulation(opts)
        got: list[np.ndarray] = []
        led = 0
        try:
            for _ in range(60):
                sim.step()
                if on:
                    st = sim.vehicle_states()
                    sim._states = None
                    want = wrappers(sim.vehicle_states)
                    assert st.ids == want.ids and st.lanes == want.lanes
                    assert type(st.ids) is type(want.ids) is tuple
                    assert all(type(x) is str for x in st.lanes)
                    for a, b in zip(
                        (st.pos_m, st.speed_mps, st.accel_mps2),
                        (want.pos_m, want.speed_mps, want.accel_mps2),
                        strict=True,
                    ):
                        assert a.dtype == b.dtype == np.float64 and a.shape == b.shape
                        assert a.tobytes() == b.tobytes()
                    ids = list(st.ids)
                    lanes = sim.lane_states(ids)
                    lanes_w = wrappers(partial(sim.lane_states, ids))
                    assert lanes[0] == lanes_w[0]
                    # The same str object for a lane ID answered again (kept, its hash cached)
                    assert all(x is y for x, y in zip(lanes[0], st.lanes, strict=True))
                    assert all(
                        x.tobytes() == y.tobytes()
                        for x, y in zip(lanes[1:], lanes_w[1:], strict=True)
                    )
                    lead = sim.leaders(ids, 100.0)
                    assert lead == wrappers(partial(sim.leaders, ids, 100.0))
                    assert all(type(r) is tuple and type(r[1]) is float for r in lead)
                    led += sum(r[0] != "" for r in lead)
                    own = sim.own_speeds(ids)
                    assert own.tobytes() == wrappers(partial(sim.own_speeds, ids)).tobytes()
                st = sim.vehicle_states()
                got += [st.pos_m.copy(), st.speed_mps.copy()]
                # Every car on an approach slowed to 80% of its speed (+0.1): sent by
                # libsumo's C++ setSpeed in one run, by the wrapper in the other.
                cmd = [
                    v
                    for v, la in zip(st.ids, st.lanes, strict=True)
                    if la.split("_")[0].endswith("si")
                ]
                speed = st.speed_mps[[st.index[v] for v in cmd]] * 0.8 + 0.1
                send = partial(sim.set_speeds, cmd, speed)
                send() if on else wrappers(send)
        finally:
            sim.close()
        if on:
            assert led > 50  # leaders were found, not only ("", -1.0)
        seen[on] = got
    assert len(seen[True]) == len(seen[False]) == 120
    assert all(a.tobytes() == b.tobytes() for a, b in zip(seen[True], seen[False], strict=True))


def test_forms_it_does_not_take_go_back_to_the_wrappers(tmp_path: Path) -> None:
    """No Python error is left where it declines; an unknown vehicle is the wrappers' to
    report (KeyError from ``lane_states``, libsumo's exception from the others)."""
    sim = Simulation(cross_options(tmp_path, cars=8))
    try:
        for _ in range(6):
            sim.step()
        ids = list(sim.vehicle_states().ids)
        assert len(ids) >= 4
        out = np.empty((2, len(ids)))
        assert lib.floats("ps", ids, out) and lib.floats("ps", tuple(ids), out)
        for bad in (np.empty((2, len(ids)), np.float32), np.empty((3, len(ids))),
                    np.empty((2, len(ids) + 1)), np.empty((2, 2 * len(ids)))[:, ::2]):  # fmt: skip
            assert not lib.floats("ps", ids, bad)
        assert not lib.floats("px", ids, out) and not lib.floats("", ids, np.empty((0, 4)))
        assert not lib.floats("ps", np.array(ids), out)  # not a list or tuple
        assert not lib.floats("ps", [*ids[:-1], 7], out)  # not a str
        unknown = [*ids[:2], "nobody"]
        assert not lib.floats("s", unknown, np.empty((1, 3)))  # SUMO's exception: declined
        assert lib.lanes(unknown) is None and lib.leaders(unknown, 50.0) is None
        assert lib.lanes([]) == [] and lib.leaders((), 50.0) == []
        assert lib.ids() == tuple(libsumo.vehicle.getIDList())
        assert all(a is b for a, b in zip(lib.ids(), lib.ids(), strict=True))  # kept
        assert not lib.send(unknown, np.zeros(3)) and not lib.send(ids, np.zeros(1))
        with pytest.raises(KeyError):
            sim.lane_states(unknown)
        with pytest.raises(libsumo.TraCIException):
            sim.leaders(unknown, 50.0)
        with pytest.raises(libsumo.TraCIException):
            sim.set_speeds(unknown, [1.0, 1.0, 1.0])
    finally:
        sim.close()


def test_the_environment_switches_it_off() -> None:
    code = "from macromicro_sumo.sumo import direct; print(direct.lib is None)"
    env = {**os.environ, "MACROMICRO_SUMO_DIRECT": "0"}
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert got.stdout.strip() == "True", got.stderr
