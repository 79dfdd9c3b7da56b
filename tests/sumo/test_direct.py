"""sumo/libsumo_cxx.cpp (``sumo.direct``): a step's per-vehicle libsumo calls on libsumo's C++
functions give what the SWIG wrappers give, to the bit, on a real SUMO run; whatever it
cannot take (an ID or output of another form, an unknown vehicle) goes back to the
wrappers, which answer or raise as before; the environment switch turns it off."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import libsumo
import numpy as np
import pytest
from cross_paths import cross_options, same_both_ways

from macromicro_sumo.sumo import direct
from macromicro_sumo.sumo.simulation import Simulation

lib = pytest.importorskip(
    "macromicro_sumo.sumo.libsumo_cxx", reason="sumo/libsumo_cxx.cpp not built"
)
OFF = os.environ.get("MACROMICRO_SUMO_DIRECT") == "0"  # switched off for this process


@pytest.fixture
def wrappers(monkeypatch: pytest.MonkeyPatch):
    """A function that runs ``f()`` with sumo/libsumo_cxx.cpp switched off (the wrappers)."""

    def run(f):
        with monkeypatch.context() as m:
            m.setattr(direct, "lib", None)
            return f()

    return run


@pytest.mark.skipif(OFF, reason="MACROMICRO_SUMO_DIRECT=0")
def test_a_runs_reads_and_commands_are_the_wrappers_to_the_bit(tmp_path: Path, wrappers) -> None:
    """Each step's states, lane states, leaders and own speeds read both ways are equal to
    the bit (same types, dtypes and shapes); the same speed commands sent both ways (by
    libsumo's C++ setSpeed, by the wrapper) move the cars alike
    (``cross_paths.same_both_ways``)."""
    assert lib.available() and direct.lib is lib

    def check(step: int, st, lanes: list, lead: list) -> None:
        assert type(st.ids) is tuple and all(type(x) is str for x in st.lanes)
        # The same str object for a lane ID answered again (kept, its hash cached)
        assert all(x is y for x, y in zip(lanes[0], st.lanes, strict=True))
        assert all(type(r) is tuple and type(r[1]) is float for r in lead)

    counts = same_both_ways(cross_options(tmp_path), wrappers, check)
    assert counts["leaders"] > 50  # leaders were found, not only ("", -1.0)


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
