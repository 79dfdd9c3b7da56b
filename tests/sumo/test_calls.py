"""sumo/calls.c (``sumo.reads``): a step's per-vehicle libsumo calls and look-ups in one C
loop each give what map and np.fromiter give, to the bit, on a real SUMO run; any operand
the loop does not take goes back to numpy's path; an argument tuple a callee keeps is not
reused."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import libsumo
import numpy as np
import pytest
from cross_paths import cross_options, same_both_ways

from macromicro_sumo.deploy.observe import Table
from macromicro_sumo.deploy.slots import VehicleSlots
from macromicro_sumo.sumo import direct, reads

calls = pytest.importorskip("macromicro_sumo.sumo.calls", reason="sumo/calls.c not built")


@pytest.fixture
def numpy_path(monkeypatch: pytest.MonkeyPatch):
    """A function that runs ``f()`` with sumo/calls.c switched off (numpy's path), and
    sumo/libsumo_cxx.cpp (libsumo's C++ functions, ``sumo.direct``): the wrappers asked."""

    def run(f):
        with monkeypatch.context() as m:
            m.setattr(reads, "calls", None)
            m.setattr(direct, "lib", None)
            return f()

    return run


def test_a_runs_reads_and_commands_are_numpys_to_the_bit(tmp_path: Path, numpy_path) -> None:
    """game/cross, 40 cars on four approaches: each step's states, lane states, leaders and
    own speeds read both ways are equal to the bit (and of the same dtypes and shapes); the
    same speed commands sent both ways (the C loop, map) move the cars alike
    (``cross_paths.same_both_ways``)."""
    counts = same_both_ways(cross_options(tmp_path), numpy_path)
    assert counts["leaders"] > 50 and counts["commanded"] > 0  # not only empty answers


def test_forms_the_loops_do_not_take_go_back_to_numpy() -> None:
    ids = ["a", "b", "c"]
    half = {"a": 0.5, "b": 1.5, "c": 2.5}.__getitem__
    out = np.full((1, 3), np.nan)
    assert calls.floats((half,), ids, out) and out.tolist() == [[0.5, 1.5, 2.5]]
    assert calls.floats((half,), ids, out[0]) and out[0].tolist() == [0.5, 1.5, 2.5]
    for bad in (np.empty(3, np.float32), np.empty(4), np.empty((3, 1)), np.empty(6)[::2]):
        assert not calls.floats((half,), ids, bad)
    assert not calls.floats((half,), np.array(ids), np.empty(3))  # not a list or tuple
    assert not calls.floats((len,), ids, np.empty(3))  # an int answered: numpy converts it
    assert reads.floats((len,), ids).tolist() == [[1.0, 1.0, 1.0]]
    assert reads.floats((half, half), ()).shape == (2, 0)
    # The look-ups: exact dicts and int values only; a missing key with no default raises
    # KeyError(key) as dict.__getitem__ does.
    code = {"a": 3, "b": 4}
    assert reads.codes(code, ["b", "x", "a"], -1).tolist() == [4, -1, 3]
    with pytest.raises(KeyError) as err:
        reads.codes(code, ["a", "x"])
    assert err.value.args == ("x",)
    assert not calls.lookup(code, ids, 0, np.empty(3, np.int32))
    assert not calls.lookup({"a": 1.0}, ["a"], 0, np.empty(1, np.int64))
    assert reads.codes({"a": np.int64(7)}, ["a"]).tolist() == [7]  # numpy's path
    assert not calls.lookup({"a": 2**70}, ["a"], 0, np.empty(1, np.int64))
    # The send: floats as Python floats, one call per item; a wrong form: map's path.
    sent: list = []
    assert calls.send(lambda v, x: sent.append((v, x)), ids, np.array([1.0, -0.0, 2.5]))
    assert sent == [("a", 1.0), ("b", -0.0), ("c", 2.5)] and type(sent[0][1]) is float
    assert not calls.send(sent.append, ids, np.array([1.0, 2.0]))
    assert not calls.send(sent.append, ids, np.array([1, 2, 3]))


def test_a_kept_argument_tuple_is_not_reused() -> None:
    """An exception keeps the tuple it was made with as its args: each its own."""
    made = calls.objects(ValueError, ["a", "b", "c"])
    assert [e.args for e in made] == [("a",), ("b",), ("c",)]
    made = calls.objects(KeyError, ("x", "y"), 2.0)
    assert [e.args for e in made] == [("x", 2.0), ("y", 2.0)]
    asked: list[str] = []

    def answer(v: str) -> float:
        asked.append(v)
        if v == "b":
            raise libsumo.TraCIException(f"Vehicle '{v}' is not known")
        return 1.0

    with pytest.raises(libsumo.TraCIException):  # the getter's own error, as from map
        calls.floats((answer,), ["a", "b", "c"], np.empty(3))
    assert asked == ["a", "b"]


def test_the_deployments_tables_read_through_the_loop() -> None:
    """``Table.codes`` and ``VehicleSlots.slots`` give what their dictionaries hold; a
    vehicle without a slot raises KeyError, which the driver's ``slots_of`` answers."""
    table = Table.of_rows({"car": (5.0, 2.5, 4.5), "truck": (12.0, 3.0, 4.0)}, (0.0, 0.0, 9.0))
    assert table.codes(["truck", "bus", "car"]).tolist() == [2, 0, 1]
    slots = VehicleSlots(2)
    for v in ("v1", "v2", "v3"):
        slots.add(v)
    assert slots.slots(["v3", "v1"]).tolist() == [2, 0]
    with pytest.raises(KeyError):
        slots.slots(["v1", "v9"])


def test_the_leader_look_ups_are_numpys(numpy_path) -> None:
    """``reads.leader_codes``: the gaps, the leaders' rows and the shape codes, as numpy's
    path gives them; a pair of another form goes to numpy's path."""
    leaders = [("b", 3.5), ("", -1.0), ("gone", 12.25), ("a", 0.0)]
    vids = ["a", "b", "c", "d"]
    index, code = {"a": 0, "b": 1, "c": 2, "d": 5}, {"a": 2, "b": 1, "gone": 3}
    got = reads.leader_codes(leaders, index, code, vids)
    want = numpy_path(partial(reads.leader_codes, leaders, index, code, vids))
    assert [g.tolist() for g in got] == [w.tolist() for w in want]
    assert got[0].tolist() == [3.5, -1.0, 12.25, 0.0]
    assert got[1].tolist() == [1, -1, -1, 0] and got[2].tolist() == [2, 1, 0, 0, 1, 0, 3, 2]
    assert [g.dtype for g in got] == [w.dtype for w in want]
    gap, row, shape = np.empty(2), np.empty(2, np.int64), np.empty(2, np.int64)
    for bad in ([("b", 1), ("a", 2.0)], [["b", 1.0], ("a", 2.0)], [("b", 1.0, 0), ("a", 2.0)]):
        assert not calls.pairs(bad, index, code, gap, row, shape)
    assert not calls.pairs([("b", 1.0)], index, code, gap, row, shape)  # outputs too long
    assert not calls.pairs([("a", 1.0), ("b", 1.0)], {"a": 0.5}, code, gap, row, shape)
    assert calls.pairs([("a", 1.0), ("b", 2.0)], index, code, gap, row, shape)
    assert (gap.tolist(), row.tolist(), shape.tolist()) == ([1.0, 2.0], [0, 1], [2, 1])
