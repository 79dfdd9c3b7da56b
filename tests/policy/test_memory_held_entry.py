"""``policy.driver_speed = "memory"`` with ``policy.driver_entry = "held"``: a driver first
seen held by what is ahead (``held_at_sight``: a leader within the free gap, not pulling
away) takes ``"drawn"``'s factor at its level, as a queued one does; a free first sight
keeps its own ratio. Drawn net 522 with ``deploy.merge_reach = "occupation"`` (stop 40):
9.8% of the drivers, first seen moving at 0.65-0.72 of the median behind their leaders,
kept the range's lowest ratio and led platoons on the one-lane edges. The default
("queued") keeps every moving first sight's ratio (netgen_corridor's)."""

import dataclasses
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from macromicro_sumo.env.driver_speed import (
    QUANTILE_LEVELS,
    DriverSpeeds,
    driver_levels,
    factors_at,
    held_at_sight,
    ratio_quantiles,
    with_driver_factors,
)
from macromicro_sumo.env.observed_drivers import FREE_BUMPER_GAP_M, FREE_HEADWAY_S, UNHELD_HEADWAY_S
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import NO_LEADER_GAP_M
from macromicro_sumo.scenario.load import load_scenario

sys.path.insert(0, str(Path(__file__).parent))
from test_driver_speed import straight_scenario  # noqa: E402

LIMIT_MPS = 24.0
Q = ratio_quantiles(np.linspace(0.8, 1.2, 41))  # median 1.0, range 0.8-1.2


def _sights(layout_gap: bool) -> tuple[np.ndarray, list[str]]:
    """First sights [v, limit, leader column, delta v] at 0.75 and 1.1 of the limit (above
    ``QUEUED_ENTRY_SHARE``: moving, not queued), each free, behind a slower car within the
    free gap, behind a faster car pulling away, and behind a standing obstacle."""
    v = np.array([0.75, 0.75, 0.75, 0.75, 1.1, 1.1, 1.1]) * LIMIT_MPS
    free_gap = v * FREE_HEADWAY_S + FREE_BUMPER_GAP_M
    gap = np.array(
        [
            NO_LEADER_GAP_M,  # no leader
            0.5 * free_gap[1],  # a slower leader near: held
            v[2] * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M + 1.0,  # faster, pulling away
            0.6 * free_gap[3],  # a red light or a lane's end: held
            1.2 * free_gap[4],  # a slower leader beyond the free gap
            0.8 * free_gap[5],  # a slower leader near: held, however fast
            0.8 * free_gap[6],  # a faster leader near, within 1 s x v + 5 m: held
        ]
    )
    gap[6] = 0.5 * (v[6] * UNHELD_HEADWAY_S + FREE_BUMPER_GAP_M)
    dv = np.array([0.0, 3.0, -4.0, v[3], 2.0, 2.0, -3.0])
    col = np.where(gap < NO_LEADER_GAP_M, gap if layout_gap else gap + 5.0, NO_LEADER_GAP_M)
    obs = np.column_stack([v, np.full(7, LIMIT_MPS), col, dv, np.full(7, LIMIT_MPS)])
    return obs, [f"e{i}" for i in range(7)]


HELD = np.array([False, True, False, True, False, True, True])


def test_held_at_sight_reads_the_leader_as_the_observed_drivers_rule() -> None:
    for layout_gap in (True, False):
        obs, _ = _sights(layout_gap)
        np.testing.assert_array_equal(held_at_sight(obs, layout_gap), HELD)


def _scenario(observation: str, entry: str | None) -> SimpleNamespace:
    policy = SimpleNamespace(driver_speed="memory", observation=observation)
    if entry is not None:
        policy.driver_entry = entry
    return SimpleNamespace(seed=522, policy=policy)


def test_a_held_first_sight_is_drawn_a_free_one_keeps_its_ratio() -> None:
    for observation, layout_gap in (("lookahead_gap", True), ("lookahead", False)):
        obs, ids = _sights(layout_gap)
        f = DriverSpeeds(Q, _scenario(observation, "held"), 1)(ids, obs)
        drawn = factors_at(Q, driver_levels(522, 1, ids))
        # Held: "drawn"'s factor at its level; free or pulling away: its own ratio, within
        # the range (0.75 -> the lowest, 0.8; 1.1 its own).
        np.testing.assert_allclose(f[HELD], drawn[HELD])
        np.testing.assert_allclose(f[~HELD], [0.8, 0.8, 1.1])
        assert not np.allclose(f[[1, 3]], 0.8)  # before: the held ones kept the lowest ratio
        # The default, "queued" (and a scenario without the setting): every ratio kept.
        for entry in ("queued", None):
            kept = DriverSpeeds(Q, _scenario(observation, entry), 1)(ids, obs)
            np.testing.assert_allclose(kept, [0.8, 0.8, 0.8, 0.8, 1.1, 1.1, 1.1])


@dataclasses.dataclass(frozen=True)
class Slots:
    """What ``with_driver_factors`` reads and replaces of a ``SectionBank``."""

    valid: np.ndarray
    hidden: np.ndarray
    driver_factor: np.ndarray | None = None


def test_stage_two_draws_a_held_generated_start() -> None:
    valid = np.ones((300, 2), dtype=bool)
    # Slot 0 generated at 0.75 of the limit 10 m behind a slower car, slot 1 free at 0.9.
    obs0 = np.tile(
        [[0.75 * LIMIT_MPS, LIMIT_MPS, 10.0, 2.0], [0.9 * LIMIT_MPS, LIMIT_MPS, 300.0, 0.0]],
        (300, 1),
    )
    bank = Slots(valid, valid)
    f = with_driver_factors(bank, "memory", Q, 11, obs0, "held", True).driver_factor
    np.testing.assert_allclose(f[:, 1], 0.9)  # free: its ratio
    assert f[:, 0].std() > 0.05 and abs(np.median(f[:, 0]) - 1.0) < 0.05  # held: drawn
    queued = with_driver_factors(bank, "memory", Q, 11, obs0, "queued", True).driver_factor
    np.testing.assert_allclose(queued, [[0.8, 0.9]] * 300)  # the default: both kept
    assert np.interp(0.5, QUANTILE_LEVELS, Q) == 1.0


def test_driver_entry_is_auto_by_default_and_checked(tmp_path: Path) -> None:
    """``policy.driver_entry``: "auto" by default (stop 47) and recorded in the scenario's
    dict, so a run trained under "queued" (before, left out) is trained again; "queued" said
    is left out (the digest it had before the key existed); "held" read; an unknown value is
    one line naming file, field and what is accepted."""
    path = straight_scenario(tmp_path, "memory")
    plain = load_scenario(path)
    assert plain.policy.driver_entry == "auto"
    assert plain.to_dict()["policy"]["driver_entry"] == "auto"
    text = path.read_text()
    digests = {}
    for value in ("queued", "held", "auto"):
        path.write_text(
            text.replace(
                'driver_speed = "memory"', f'driver_speed = "memory"\ndriver_entry = "{value}"'
            )
        )
        sc = load_scenario(path)
        assert sc.policy.driver_entry == value
        assert ("driver_entry" in sc.to_dict()["policy"]) is (value != "queued")
        digests[value] = sc.digest()
    assert digests["auto"] == plain.digest() and len(set(digests.values())) == 3
    path.write_text(
        text.replace('driver_speed = "memory"', 'driver_speed = "memory"\ndriver_entry = "late"')
    )
    with pytest.raises(UserError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert "\n" not in msg and "policy.driver_entry" in msg and "'queued', 'held', 'auto'" in msg, (
        msg
    )
