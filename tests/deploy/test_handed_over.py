"""``MergeYield.handed_over``: ``merges`` from ``handover_m``'s reach and ``usable_m``'s
distance left, with the shortcut where no driven vehicle must change lane and none is
merging (every lane end inf: a finite one comes with its offset). The shortcut answers
what the full path answers (None: all commanded), without reading the occupations; a
vehicle with an offset, or one merging, takes the full path. The answers of the full
path are those of the three calls in a row, as ``deploy.drivers`` made them before."""

from __future__ import annotations

import types

import numpy as np

from macromicro_sumo.deploy.merge_yield import MergeYield
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.slots import VehicleSlots

N = 6


class Host(MergeYield):
    """The state the merge code reads of ``SectionSpeedDriver``, counting ``usable_m``."""

    def __init__(self) -> None:
        self.slots = VehicleSlots()
        for i in range(N):
            self.slots.add(f"v{i}")
        self.sc = types.SimpleNamespace(simulation=types.SimpleNamespace(step_length_s=0.5))
        self.occupation, self.merging, self.stats, self.mode = False, set(), DriveStats(), 0
        self.usable_calls = 0

    def usable_m(self, ahead_m, rows, lanes, slots, st):  # type: ignore[no-untyped-def]
        self.usable_calls += 1
        return super().usable_m(ahead_m, rows, lanes, slots, st)


def _both(offsets: list[int], ahead: list[float]) -> tuple[Host, object, object]:
    """``handed_over`` and the three calls it stands for, each on a host of its own with
    the same lane-end offsets and distances (no SUMO needed: nobody is handed over)."""
    vids = [f"v{i}" for i in range(N)]
    out = []
    hosts = (Host(), Host())
    for h in hosts:
        slots = h.slots.slots(vids)
        h.slots.lane_end.offset[slots] = offsets
        h.slots.with_gap[slots] = 7.5  # length + minGap
    speed, rows, a = np.linspace(10.0, 20.0, N), np.arange(N), np.array(ahead)
    new, old = hosts
    slots = new.slots.slots(vids)
    out.append(new.handed_over(None, vids, a, rows, ["e_0"] * N, slots, speed, None))
    reach = old.handover_m(vids, slots, speed)
    reach = np.zeros(N) if reach is None else reach
    usable = old.usable_m(a, rows, ["e_0"] * N, slots, None)
    out.append(old.merges(None, vids, usable, reach))
    assert np.array_equal(new.slots.lookahead_mps, old.slots.lookahead_mps, equal_nan=True)
    return new, out[0], out[1]


def test_no_offset_and_nobody_merging_skips_the_occupations() -> None:
    new, got, full = _both([0] * N, [np.inf] * N)
    assert got is None and full is None
    assert new.usable_calls == 0  # the shortcut: no distance read
    assert not np.isnan(new.slots.lookahead_mps[:N]).any()  # the look-ahead still updated


def test_an_offset_takes_the_full_path_with_the_same_answer() -> None:
    # v2 must change lane 2 km ahead: beyond its reach, so still commanded (None).
    new, got, full = _both([0, 0, 1, 0, 0, 0], [np.inf, np.inf, 2000.0, np.inf, np.inf, np.inf])
    assert new.usable_calls == 1
    assert got is None and full is None
