"""``policy.driver_entry = "auto"`` (``env.driver_speed.entry_choice``): "held" where the
observed drivers' own held first sights are below their speed ("insertion" where their free
ones are as well), "queued" where they are at it. Real SUMO: the same road and demand, inserted at ``departSpeed="max"`` (behind a slow
platoon: the safe speed, below the own) or ``"desired"`` (SUMO waits until the own speed is
safe), as drawn 522 and netgen_corridor insert theirs (stop 44)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import dump_toml, netconvert

from macromicro_sumo.env import driver_speed
from macromicro_sumo.env.driver_speed import (
    ENTRY_AT_OWN_SHARE,
    MIN_HELD_SIGHTS,
    QUANTILE_LEVELS,
    DriverSpeeds,
    entry_choice,
    first_sights,
    held_at_sight,
    resolved_entry,
)
from macromicro_sumo.env.driver_speed_ratios import ObservedDrivers
from macromicro_sumo.env.observed_drivers import observed_drivers
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

LIMIT_MPS = 30.0


def platoon_scenario(folder: Path, depart_speed: str) -> Path:
    """One lane for 600 m, then two for 1,400 m, at 30 m/s: a slow car (speedFactor 0.5)
    every 30 s and a car at the limit every 3 s behind it, which pass it where the second
    lane begins; every vehicle instrumented."""
    folder.mkdir(parents=True, exist_ok=True)
    net = netconvert(
        folder,
        '<node id="a" x="0" y="0"/>\n<node id="b" x="600" y="0"/>\n<node id="c" x="2000" y="0"/>',
        f'<edge id="E1" from="a" to="b" numLanes="1" speed="{LIMIT_MPS}"/>\n'
        f'<edge id="E2" from="b" to="c" numLanes="2" speed="{LIMIT_MPS}"/>',
    )
    routes = folder / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vType id="slow" length="5" minGap="2.5" speedFactor="0.5" speedDev="0"/>\n'
        '    <vType id="car" length="5" minGap="2.5" speedFactor="1.0" speedDev="0"/>\n'
        '    <route id="r" edges="E1 E2"/>\n'
        f'    <flow id="s" type="slow" route="r" begin="0" end="3600" period="30" '
        f'departSpeed="{depart_speed}"/>\n'
        f'    <flow id="c" type="car" route="r" begin="1" end="3600" period="3" '
        f'departSpeed="{depart_speed}"/>\n'
        "</routes>\n"
    )
    table = {
        "name": f"platoon_{depart_speed}",
        "seed": 5,
        "network": {"kind": "sumo", "net_file": str(net), "route_files": [str(routes)]},
        "section": {"edges": ["E1", "E2"]},
        "instrumented": {"penetration": 1.0},
        "simulation": {"warmup_s": 120.0, "duration_s": 240.0, "n_runs": 1},
        "detectors": {"interval_s": 60.0, "auto_spacing_m": 1000.0},
        "policy": {"prior": "gipps", "driver_speed": "memory"},
    }
    path = folder / "platoon.toml"
    path.write_text(dump_toml(table))
    return path


@pytest.mark.parametrize(("depart_speed", "entry"), [("max", "held"), ("desired", "queued")])
def test_auto_reads_whether_the_observed_held_first_sights_are_at_their_speed(
    tmp_path: Path, depart_speed: str, entry: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    sc = load_scenario(platoon_scenario(tmp_path, depart_speed))
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    drivers = observed_drivers(sc, truth, truth.runs)
    choice = entry_choice(drivers, gap_layout=False)
    # Held first sights that "queued" keeps on both (measured: 17 and 57; with the ones
    # it draws as well, stop 44: 43 and 67), so the rule reads them on both.
    assert (choice.entry, choice.held_sights >= MIN_HELD_SIGHTS) == (entry, True)
    if entry == "held":  # inserted at the safe speed behind the platoon (measured 0.78)
        assert choice.at_own < 0.9
    else:  # inserted once the own speed is safe: held, at it (measured 1.00)
        assert choice.at_own >= ENTRY_AT_OWN_SHARE
    # "auto" resolved on the same drivers, as every stage that builds drivers resolves it;
    # unresolved, no driver reads it; any other value stays as it is
    auto = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, driver_entry="auto"))
    with pytest.raises(ValueError, match="policy.driver_entry 'auto'"):
        DriverSpeeds(np.ones(len(QUANTILE_LEVELS)), auto, 0)
    resolved, got = resolved_entry(auto, truth, truth.runs)
    assert got == choice and resolved.policy.driver_entry == entry
    # no memo (stop 46): each call reads the observed drivers of its runs, the same choice
    # each time; a stage resolves once where it loads the truth and passes the result down
    reads = []
    monkeypatch.setattr(driver_speed, "observed_drivers", lambda *a: reads.append(a) or drivers)
    assert resolved_entry(auto, truth, truth.runs)[1] == got and len(reads) == 1
    assert resolved_entry(auto, truth, truth.runs[:1].astype(np.int32))[1] == got
    assert len(reads) == 2 and reads[1][2].tolist() == truth.runs[:1].tolist()
    assert DriverSpeeds(np.ones(len(QUANTILE_LEVELS)), resolved, 0).entry == entry
    queued = dataclasses.replace(sc, policy=dataclasses.replace(sc.policy, driver_entry="queued"))
    assert resolved_entry(queued, truth, truth.runs) == (queued, None)
    drawn = dataclasses.replace(auto, policy=dataclasses.replace(auto.policy, driver_speed="drawn"))
    assert resolved_entry(drawn, truth, truth.runs)[0].policy.driver_entry == "queued"


def _drivers(first: np.ndarray, later_v: float, tops: list[float]) -> ObservedDrivers:
    """Observed drivers d0.. with first sights ``first`` ([v, limit, spacing, delta v]), a
    later free pair at ``later_v`` each, and their tops (exact ratios) ``tops``."""
    n = len(first)
    later = np.column_stack(
        [np.full(n, later_v), first[:, 1], np.full(n, NO_LEADER_GAP_M), np.zeros(n)]
    )
    keys = [(0, f"d{i}") for i in range(n)]
    # time order within the run: each driver's first sight before any later pair
    obs = np.concatenate([first, later])
    return ObservedDrivers(
        {k: t for k, t in zip(keys, tops, strict=True)}, obs, np.zeros(2 * n), keys + keys
    )


def test_auto_reads_each_drivers_first_pair_and_needs_enough_held_ones() -> None:
    n = MIN_HELD_SIGHTS + 2
    # behind a slower leader 10 m ahead at 0.7 of the limit: held
    first = np.column_stack(
        [np.full(n, 0.7 * LIMIT_MPS), np.full(n, LIMIT_MPS), np.full(n, 15.0), np.full(n, 2.0)]
    )
    assert held_at_sight(first, gap_layout=False).all()
    np.testing.assert_array_equal(first_sights(_drivers(first, 29.0, [1.0] * n)), np.arange(n))
    below = entry_choice(_drivers(first, 29.0, [1.0] * n), gap_layout=False)
    assert (below.entry, below.held_sights) == ("held", n)
    assert below.at_own == pytest.approx(0.7)
    # the same first sights at the drivers' own top: their speed says their desire
    at = entry_choice(_drivers(first, 21.0, [0.7] * n), gap_layout=False)
    assert (at.entry, at.at_own) == ("queued", pytest.approx(1.0))
    # too few held first sights: "queued", the default's rule
    few = _drivers(first[: MIN_HELD_SIGHTS - 1], 29.0, [1.0] * (MIN_HELD_SIGHTS - 1))
    assert entry_choice(few, gap_layout=False).entry == "queued"
    # free first sights (no leader) are not read, however slow
    free = first.copy()
    free[:, 2] = NO_LEADER_GAP_M
    none = entry_choice(_drivers(free, 29.0, [1.0] * n), gap_layout=False)
    assert (none.entry, none.held_sights) == ("queued", 0)


def test_auto_is_insertion_where_the_free_first_sights_are_below_their_tops_too() -> None:
    """Held first sights below their tops ("held"); free ones (nobody ahead) below theirs as
    well: the net inserts slower than its drivers want beyond the free gap, "insertion"
    (drawn 522: 5 free sights at 0.806, stop 47); at their tops, or too few: "held"."""
    n = MIN_HELD_SIGHTS + 2
    held = np.column_stack(
        [np.full(n, 0.7 * LIMIT_MPS), np.full(n, LIMIT_MPS), np.full(n, 15.0), np.full(n, 2.0)]
    )
    free = held.copy()
    free[:, 2] = NO_LEADER_GAP_M
    first = np.concatenate([held, free])
    slow = entry_choice(_drivers(first, 29.0, [1.0] * 2 * n), gap_layout=False)
    assert (slow.entry, slow.held_sights, slow.free_sights) == ("insertion", n, n)
    assert slow.free_at_own == pytest.approx(0.7)
    # the free ones at their own tops: "held", as before stop 48
    tops = [1.0] * n + [0.7] * n
    at = entry_choice(_drivers(first, 29.0, tops), gap_layout=False)
    assert (at.entry, at.free_at_own) == ("held", pytest.approx(1.0))
    # too few free ones to read: "held"
    few = np.concatenate([held, free[: MIN_HELD_SIGHTS - 1]])
    k = n + MIN_HELD_SIGHTS - 1
    assert entry_choice(_drivers(few, 29.0, [1.0] * k), gap_layout=False).entry == "held"
