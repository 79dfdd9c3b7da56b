"""A standing queue's start as SUMO's Krauss drivers': ``deploy.start_dawdle``, a driven
vehicle's speed command below its accel lowered by the mean of the Krauss dawdle of a
starting driver, v' (1 - sigma dt / 2), after the safe speed's cap and the floor
(``deploy.safety.start_dawdled``); ``deploy.start_reaction_s``, a standing vehicle's
command and floor at most the Krauss safe speed with that reaction time. The rules on
their own (numpy), through ``speed_commands``, then a queue at a real SUMO light driven
full throttle, whose cars the one-step safe speed starts: later with them, without a
collision."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from deploy_nets import queue_at_light
from test_floor_reaction import GREEN_S, queue_starts

from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import reaction_safe_speed, speed_commands, start_dawdled
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.scenario.load import load_scenario

DT = 0.5


def test_only_commands_below_the_accel_dawdle() -> None:
    """Below a (as a number) a command loses sigma dt / 2 of itself (sigma 0.5, dt 0.5:
    12.5%), at or above a it is kept to the bit; per vehicle accels too."""
    cmd = np.array([0.0, 0.4, 1.3, 2.59, 2.6, 9.0])
    got = start_dawdled(cmd, 2.6, 0.5, DT)
    np.testing.assert_array_equal(got[[0, 4, 5]], cmd[[0, 4, 5]])
    np.testing.assert_allclose(got[1:4], cmd[1:4] * 0.875, rtol=0, atol=1e-15)
    truck = start_dawdled(np.array([1.3, 1.3]), np.array([2.6, 1.3]), 0.5, DT)
    assert truck[0] == pytest.approx(1.3 * 0.875) and truck[1] == 1.3
    # Never braking beyond the decel: a car at 3.1 m/s braking at 4.5 to 0.85 keeps 0.85
    # (SUMO's finalizeSpeed), one commanded lower keeps its command, one at 1 m/s dawdles.
    least = np.array([3.1, 3.1, 1.0]) - 4.5 * DT
    got = start_dawdled(np.array([0.85, 0.5, 1.2]), 2.6, 0.5, DT, least)
    np.testing.assert_allclose(got, [0.85, 0.5, 1.2 * 0.875], rtol=0, atol=1e-15)


def _queue_scenario(tmp_path: Path, sigma: float, reaction_s: float = 0.0) -> Path:
    """``deploy_nets.queue_at_light`` with the start dawdle ``sigma`` and reaction."""
    # Each set, 0 included (their defaults moved at stop 49), on every driven vehicle.
    deploy = {"start_dawdle": sigma, "start_reaction_s": reaction_s, "start_rules": "all"}
    return queue_at_light(tmp_path / f"queue_{sigma}_{reaction_s}.toml", GREEN_S, deploy)


def test_speed_commands_start_later(tmp_path: Path) -> None:
    """A standing car 0.5 m behind a leader moving off at 1 m/s, its policy full throttle:
    without the settings its command is the one-step safe speed (the cap); with sigma 0.5
    that times 0.875; with a reaction of 1 s the safe speed with it (below the one-step
    one), and with both that times 0.875; a car at 8 m/s free ahead keeps its command
    (above a, not standing)."""
    obs = np.zeros((2, 4))
    obs[:, 0] = [0.0, 8.0]  # own speed; column 1 the limit, 3 the closing speed
    obs[:, 1] = 14.0
    obs[:, 3] = [-1.0, 0.0]
    gap, decel = np.array([0.5, 400.0]), np.full(2, 4.5)

    def layer() -> tuple[np.ndarray, ...]:
        return gap, decel, decel, np.full(2, -1)

    got = {}
    for sigma, reaction in ((0.0, 0.0), (0.5, 0.0), (0.0, 1.0), (0.5, 1.0)):
        sc = load_scenario(_queue_scenario(tmp_path / f"{sigma}_{reaction}", sigma, reaction))
        act = lambda obs: np.full(len(obs), 2.6)  # noqa: E731
        got[sigma, reaction] = speed_commands(sc, act, "sumo", DriveStats(), obs, layer)
    v_l, b = np.array([1.0]), decel[:1]
    cap = safe_speed(gap[:1], v_l, b, b, DT)[0]
    late = reaction_safe_speed(gap[:1], v_l, b, b, DT, 1.0)[0]
    assert late < cap < 2.6 * DT  # the caps bind, not the acceleration
    assert got[0.0, 0.0][0] == pytest.approx(cap)
    assert got[0.5, 0.0][0] == pytest.approx(0.875 * cap)
    assert got[0.0, 1.0][0] == pytest.approx(late)
    assert got[0.5, 1.0][0] == pytest.approx(0.875 * late)
    for k in got:
        assert got[k][1] == pytest.approx(8.0 + 2.6 * DT)


def test_the_rules_start_a_full_throttle_queue_later(tmp_path: Path) -> None:
    """A standing queue driven full throttle at a real SUMO light: with one-step safe
    speeds each car moves off (above 0.5 m/s) the step after its leader (0.5 s a car;
    1164's policy 0.52-0.58 s, the truth's Krauss drivers 0.84-0.95 s); the dawdle alone
    (sigma 0.5) delays few; the reaction of 1 s, SUMO's tau, with it about 0.8 s a car; never
    sooner than a step; none collides or teleports."""
    lags = {}
    for sigma, reaction in ((0.0, 0.0), (0.5, 0.0), (0.5, 1.0)):
        toml = _queue_scenario(tmp_path / f"{sigma}_{reaction}", sigma, reaction)
        starts, stats = queue_starts(toml, 1)  # full throttle: the cap alone starts them
        assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
        assert len(starts) >= 8, starts  # the queue stood
        lags[sigma, reaction] = starts.diff().dropna()
    assert (lags[0.0, 0.0] == DT).all(), lags[0.0, 0.0].tolist()
    assert lags[0.5, 0.0].mean() >= DT and (lags[0.5, 0.0] >= DT).all()
    assert lags[0.5, 1.0].mean() >= 0.7, lags[0.5, 1.0].tolist()
    assert (lags[0.5, 1.0] >= DT).all(), lags[0.5, 1.0].tolist()


def test_a_sigma_out_of_range_is_refused(tmp_path: Path) -> None:
    """A sigma above 1 or a reaction below 0 is a one-line error naming the field."""
    with pytest.raises(UserError, match="start_dawdle"):
        load_scenario(_queue_scenario(tmp_path / "s", 1.5))
    with pytest.raises(UserError, match="start_reaction_s"):
        load_scenario(_queue_scenario(tmp_path / "r", 0.0, -1.0))
