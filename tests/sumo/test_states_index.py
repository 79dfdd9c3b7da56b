"""``VehicleStates.index``: vehicle ID -> row, computed at the first read and kept in the
instance (later reads are plain attribute reads), not a field (equality and repr as before)."""

from __future__ import annotations

import dataclasses

import numpy as np

from macromicro_sumo.sumo.states import VehicleStates


def _states(ids: tuple[str, ...]) -> VehicleStates:
    n = len(ids)
    return VehicleStates(ids, ["e_0"] * n, np.arange(n, dtype=float), np.ones(n), np.zeros(n))


def test_the_index_maps_each_vehicle_to_its_row_once() -> None:
    st = _states(("a", "b", "c"))
    assert "index" not in st.__dict__
    index = st.index
    assert index == {"a": 0, "b": 1, "c": 2}
    assert st.__dict__["index"] is index and st.index is index  # kept, not rebuilt
    assert _states(("x",)).index == {"x": 0}  # per instance
    assert VehicleStates.index.__doc__ == "Vehicle ID -> row."


def test_the_index_is_no_field() -> None:
    a, b = _states(("a", "b")), _states(("a", "b"))
    _ = a.index  # read on one of them only
    assert [f.name for f in dataclasses.fields(a)] == [
        "ids",
        "lanes",
        "pos_m",
        "speed_mps",
        "accel_mps2",
    ]
    assert "index" not in repr(a)
    assert a.ids == b.ids and a.lanes == b.lanes
