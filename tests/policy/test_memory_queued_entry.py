"""``policy.driver_speed = "memory"``: a driver first seen queued (slower than
``QUEUED_ENTRY_SHARE`` of the observed median desired speed) takes ``"drawn"``'s factor at
its own level, not the slowest observed driver's. Drawn net 522 (stop 38): the lane drop's
queue reached the entry, 63% of the deployed drivers kept 0.72 of the median and led
platoons at 16.8 m/s on the one-lane edges where the truth's stream ran 20."""

import dataclasses
from types import SimpleNamespace

import numpy as np

from macromicro_sumo.env.driver_speed import (
    QUANTILE_LEVELS,
    QUEUED_ENTRY_SHARE,
    DriverSpeeds,
    driver_levels,
    entry_factors,
    factors_at,
    ratio_quantiles,
    relative,
    with_driver_factors,
)

LIMIT_MPS = 24.0


def _drivers(q: np.ndarray, kind: str) -> DriverSpeeds:
    policy = SimpleNamespace(driver_speed=kind, observation="paper")
    return DriverSpeeds(q, SimpleNamespace(seed=522, policy=policy), 1)


def test_a_queued_entry_is_drawn_a_slow_moving_one_keeps_the_range() -> None:
    q = ratio_quantiles(np.linspace(0.8, 1.2, 41))  # median 1.0, slowest 0.8
    speed = np.array([0.0, 0.6, 0.7, 0.9, 1.1]) * LIMIT_MPS
    levels = np.array([0.9, 0.1, 0.9, 0.9, 0.9])
    assert 0.6 < QUEUED_ENTRY_SHARE < 0.7  # the cases below straddle the threshold
    f = entry_factors(q, speed, np.full(5, LIMIT_MPS), levels)
    # Queued (0 and 0.6 < 0.65): the factor at its level; moving at 0.7: the slowest observed
    # ratio as before; free: its own.
    np.testing.assert_allclose(f[:2], factors_at(q, levels[:2]))
    assert f[0] > 1.1 and f[1] < 0.9
    np.testing.assert_allclose(f[2:], [0.8, 0.9, 1.1])
    # Without levels: every one within the range, as before.
    np.testing.assert_allclose(
        entry_factors(q, speed, np.full(5, LIMIT_MPS)), [0.8, 0.8, 0.8, 0.9, 1.1]
    )


def test_deployed_drivers_entering_a_queue_get_drawns_factors() -> None:
    # 522's checkpoint's ratios: the slowest 0.72 of the median.
    q = ratio_quantiles(np.r_[0.71, np.linspace(0.82, 1.16, 40)])
    ids = [f"main0.{i}" for i in range(300)]
    standing = np.tile([0.0, LIMIT_MPS, 3.0, 0.0], (300, 1))
    f = _drivers(q, "memory")(ids, standing)
    # Before: all 300 at relative(q)[0] = 0.72; now the same factors as "drawn" gives them.
    assert relative(q)[0] < 0.75
    np.testing.assert_array_equal(f, _drivers(q, "drawn")(ids, standing))
    np.testing.assert_array_equal(f, factors_at(q, driver_levels(522, 1, ids)))
    assert np.median(f) > 0.95 and np.mean(f <= relative(q)[0] + 1e-9) < 0.05
    # A free entry keeps its own ratio.
    med = float(np.interp(0.5, QUANTILE_LEVELS, q))
    free = np.tile([1.05 * med * LIMIT_MPS, LIMIT_MPS, 300.0, 0.0], (3, 1))
    np.testing.assert_allclose(_drivers(q, "memory")(["a", "b", "c"], free), 1.05)


@dataclasses.dataclass(frozen=True)
class Slots:
    """What ``with_driver_factors`` reads and replaces of a ``SectionBank``."""

    valid: np.ndarray
    hidden: np.ndarray
    driver_factor: np.ndarray | None = None


def test_stage_two_draws_a_queued_generated_start_seeded() -> None:
    valid = np.ones((200, 2), dtype=bool)
    q = ratio_quantiles(np.linspace(0.8, 1.2, 41))
    # Slot 0 generated standing 3 m behind its leader, slot 1 free at 0.9.
    obs0 = np.tile([[0.0, LIMIT_MPS, 3.0, 0.0], [0.9 * LIMIT_MPS, LIMIT_MPS, 300.0, 0.0]], (200, 1))

    def factors(seed: int) -> np.ndarray:
        return with_driver_factors(Slots(valid, valid), "memory", q, seed, obs0).driver_factor

    f = factors(11)
    np.testing.assert_allclose(f[:, 1], 0.9)  # free start: its ratio
    assert f[:, 0].std() > 0.05 and abs(np.median(f[:, 0]) - 1.0) < 0.05  # queued: drawn
    np.testing.assert_array_equal(f, factors(11))  # seeded
    assert not np.array_equal(f, factors(12))
