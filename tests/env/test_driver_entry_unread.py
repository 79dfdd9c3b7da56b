"""``policy.driver_entry`` is read by "memory" drivers only: with ``driver_speed = "drawn"`` an
unresolved "auto" (a demand episode's or the warm-up's drivers built from the scenario as it is
set) is "queued" and the factors are drawn's; a "memory" driver still refuses it unresolved."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, DriverSpeeds, driver_entry


def _scenario(kind: str, entry: str) -> SimpleNamespace:
    policy = SimpleNamespace(driver_speed=kind, driver_entry=entry, observation="paper")
    return SimpleNamespace(seed=7, policy=policy, source="s.toml")


def test_an_unresolved_auto_is_unread_by_drawn_drivers_and_refused_by_memory_ones() -> None:
    q = np.linspace(0.8, 1.25, len(QUANTILE_LEVELS))
    ids = [f"v{i}" for i in range(20)]
    drawn = DriverSpeeds(q, _scenario("drawn", "auto"), 3)
    assert drawn.entry == "queued" == driver_entry(_scenario("drawn", "held"))
    # the same factors as under the entry it had before: drawn's, per (seed, run, vehicle)
    np.testing.assert_array_equal(
        drawn(ids, None), DriverSpeeds(q, _scenario("drawn", "queued"), 3)(ids, None)
    )
    assert len(set(drawn(ids, None).tolist())) > 1
    assert driver_entry(_scenario("memory", "held")) == "held"
    with pytest.raises(ValueError, match=r"s\.toml: policy\.driver_entry 'auto' is resolved"):
        DriverSpeeds(q, _scenario("memory", "auto"), 3)
