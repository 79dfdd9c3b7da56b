"""scripts/entry_choice.py's free first sights: the observed drivers' first sights that no rule
draws (not held by what is ahead, at least QUEUED_ENTRY_SHARE of the median) and their median
first-sight v / limit over their driver's top: below 1 where the net inserts vehicles slower
than they want (drawn 522: 5 at 0.806), 1 where at their own speed (every other net, stop 47)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from conftest import ROOT

from macromicro_sumo.env.driver_speed import QUEUED_ENTRY_SHARE, held_at_sight
from macromicro_sumo.env.driver_speed_ratios import ObservedDrivers
from macromicro_sumo.road.section import NO_LEADER_GAP_M

_spec = importlib.util.spec_from_file_location("entry_choice", ROOT / "scripts" / "entry_choice.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)

LIMIT_MPS = 30.0


def _drivers(first: np.ndarray, tops: list[float]) -> ObservedDrivers:
    """Observed drivers d0.. with first sights ``first`` ([v, limit, spacing, delta v]), a
    later free pair at the limit each, and their exact tops ``tops``."""
    n = len(first)
    later = np.column_stack(
        [np.full(n, LIMIT_MPS), first[:, 1], np.full(n, NO_LEADER_GAP_M), np.zeros(n)]
    )
    keys = [(0, f"d{i}") for i in range(n)]
    return ObservedDrivers(
        dict(zip(keys, tops, strict=True)),
        np.concatenate([first, later]),
        np.zeros(2 * n),
        keys + keys,
    )


def _sights(v: float, spacing_m: float, n: int) -> np.ndarray:
    return np.column_stack(
        [np.full(n, v), np.full(n, LIMIT_MPS), np.full(n, spacing_m), np.full(n, 2.0)]
    )


def test_free_sights_are_those_no_rule_draws_and_their_speed_against_their_top() -> None:
    n = 6
    free = _sights(0.8 * LIMIT_MPS, NO_LEADER_GAP_M, n)  # nobody ahead, at 0.8 of the limit
    held = _sights(0.8 * LIMIT_MPS, 15.0, n)  # a slower leader 15 m ahead
    queued = _sights(0.1 * LIMIT_MPS, NO_LEADER_GAP_M, n)  # crawling: below the share
    assert not held_at_sight(free, False).any() and held_at_sight(held, False).all()
    first = np.concatenate([free, held, queued])
    got = script.free_sights(_drivers(first, [1.0] * 3 * n), False, "kaplan_meier")
    assert got == (n, pytest.approx(0.8))  # the free ones only, at 0.8 of their tops
    # at their own top: 1
    at_own = script.free_sights(_drivers(free, [0.8] * n), False, "kaplan_meier")
    assert at_own == (n, pytest.approx(1.0))
    # none free (all held or queued): 0 and NaN; no observed driver at all: the same
    none = script.free_sights(
        _drivers(np.concatenate([held, queued]), [1.0] * 2 * n), False, "kaplan_meier"
    )
    assert none[0] == 0 and np.isnan(none[1])
    empty = ObservedDrivers({}, np.empty((0, 4)), np.empty(0), [])
    assert script.free_sights(empty, False, "kaplan_meier")[0] == 0
    assert 0.1 < QUEUED_ENTRY_SHARE < 0.8  # the sights above are on the sides they are meant to be


def test_insertion_sights_split_the_free_ones_at_the_insertion_speed() -> None:
    """A free sight 60 m behind a leader at 18 m/s, at Krauss's safe speed there (what SUMO
    inserts at with departSpeed "max"), is counted apart from one with nobody ahead."""
    n = 6
    gap, v_lead = 60.0, 18.0
    vsafe = -4.5 + np.sqrt(4.5**2 + v_lead**2 + 2 * 4.5 * (gap - 2.5))
    ins = _sights(vsafe, gap + 5.0, n)  # spacing layout: the gap plus a car's length
    ins[:, 3] = vsafe - v_lead
    free = _sights(0.8 * LIMIT_MPS, NO_LEADER_GAP_M, n)
    assert not held_at_sight(ins, False).any()
    tops = [vsafe / LIMIT_MPS / 0.8] * n + [0.8] * n  # the inserted ones at 0.8 of their tops
    got = script.insertion_sights(
        _drivers(np.concatenate([ins, free]), tops), False, "kaplan_meier"
    )
    assert got == (n, pytest.approx(0.8), pytest.approx(1.0))
    none = script.insertion_sights(_drivers(free, [0.8] * n), False, "kaplan_meier")
    assert none[0] == 0 and np.isnan(none[1]) and none[2] == pytest.approx(1.0)
