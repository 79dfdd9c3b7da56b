"""``deploy.safety_floor_reaction_s``: the safety layer's floor capped at SUMO's Krauss safe
speed with a reaction time (``deploy.safety.reaction_safe_speed``) instead of one step, so
that a car of a standing queue is lifted later and slower behind its leader. The closed form
against SUMO's one-step safe speed and its own stopping distance (numpy), then a queue at a
real SUMO light started by the floor alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from deploy_nets import queue_at_light
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import reaction_safe_speed, speed_commands
from macromicro_sumo.road.physics import brake_gap, safe_speed
from macromicro_sumo.road.section import NO_LEADER_GAP_M, read_section
from macromicro_sumo.scenario.load import load_scenario

DT = 0.5
GREEN_S = 80.0  # the queue's light turns green [s]


def _states(n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return (
        rng.uniform(0.0, 80.0, n),  # gap
        rng.uniform(0.0, 30.0, n),  # leader speed
        rng.uniform(1.0, 6.0, n),  # decel
        rng.uniform(1.0, 8.0, n),  # leader decel
    )


def test_one_step_reaction_is_the_caps_safe_speed() -> None:
    """With the reaction one step it is ``safe_speed`` (SUMO's Euler form), within
    rounding, over seeded states; no leader (gap ``NO_LEADER_GAP_M`` or more): inf."""
    gap, v_l, b, b_l = _states(20_000, 1)
    got = reaction_safe_speed(gap, v_l, b, b_l, DT, DT)
    np.testing.assert_allclose(got, safe_speed(gap, v_l, b, b_l, DT), rtol=0, atol=1e-12)
    far = reaction_safe_speed(np.array([NO_LEADER_GAP_M, 5.0]), np.zeros(2), 4.5, 4.5, DT, 1.0)
    assert far[0] == np.inf and np.isfinite(far[1])


@pytest.mark.parametrize("tau", [0.5, 1.0, 1.107, 2.0])
def test_the_speed_stops_in_the_room_with_its_reaction(tau: float) -> None:
    """The speed it returns, held for the reaction and braked at b in Euler steps after
    it, stops exactly in the room gap + brake_gap(v_l, max(b, b_l)): v tau +
    brake_gap(v, b) equals it (the fastest such speed), and a longer reaction is slower."""
    gap, v_l, b, b_l = _states(20_000, 2)
    v = reaction_safe_speed(gap, v_l, b, b_l, DT, tau)
    room = gap + brake_gap(v_l, np.maximum(b, b_l), DT)
    np.testing.assert_allclose(v * tau + brake_gap(v, b, DT), room, rtol=1e-12, atol=1e-9)
    longer = reaction_safe_speed(gap, v_l, b, b_l, DT, tau + 0.5)
    assert (longer < v).all()


def test_only_a_standing_vehicles_floor_waits(tmp_path: Path) -> None:
    """``speed_commands`` with a policy that always brakes: two cars at 0 and 5 m/s, 0.5
    and 8 m behind a leader at their speed. With ``safety_floor_reaction_s`` = 1 the
    standing car is lifted to ``reaction_safe_speed``'s (half the one-step room / dt), the
    moving one to the same floor as without it (``STANDING_BELOW_MPS``)."""
    obs = np.zeros((2, 4))
    obs[:, 0] = [0.0, 5.0]  # own speed; column 1 the limit, 3 the closing speed
    obs[:, 1] = 14.0
    gap, decel = np.array([0.5, 8.0]), np.full(2, 4.5)

    def layer() -> tuple[np.ndarray, ...]:
        return gap, decel, decel, np.full(2, -1)

    got = {}
    for reaction in (0.0, 1.0):
        sc = load_scenario(_queue_scenario(tmp_path / str(reaction), reaction))
        act = lambda obs: np.full(len(obs), -4.5)  # noqa: E731
        got[reaction] = speed_commands(sc, act, "sumo", DriveStats(), obs, layer)
    one_step = safe_speed(gap, obs[:, 0], decel, decel, DT)
    assert got[0.0][0] == pytest.approx(min(one_step[0], 0.0 + 2.6 * DT))
    assert got[1.0][0] == pytest.approx(reaction_safe_speed(gap, obs[:, 0], 4.5, 4.5, DT, 1.0)[0])
    assert got[1.0][0] == pytest.approx(0.5 * got[0.0][0])  # room / tau against room / dt
    assert got[1.0][1] == got[0.0][1] == pytest.approx(0.2 * 14.0)


def _queue_scenario(tmp_path: Path, reaction_s: float) -> Path:
    """``deploy_nets.queue_at_light`` with the floor on everyone and its reaction (the
    always-braking policy's floor brings the cars at 2.8 m/s)."""
    deploy = {"safety_floor_reaction_s": reaction_s} if reaction_s else {}
    # The start rules off (their defaults since stop 49): the floor's reaction alone.
    deploy = {"safety_floor_on": "all", "start_dawdle": 0.0, "start_reaction_s": 0.0, **deploy}
    return queue_at_light(tmp_path / f"queue_{reaction_s}.toml", GREEN_S, deploy)


def queue_starts(toml: Path, bound: int) -> tuple[pd.Series, dict]:
    """Each queued car's start after the green [s] (its first step above 0.5 m/s), in queue
    order, of ``deploy_nets.queue_at_light``'s scenario ``toml``, the cars driven at the
    accel bound ``bound`` (0: always braking, the floor alone starts them; 1: full throttle,
    the safe speed's cap alone)."""
    sc = load_scenario(toml)
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    a = sc.bounds.accel_mps2[bound]
    drv = SectionSpeedDriver(sc, section, 0, lambda obs: np.full(len(obs), a), "sumo")
    light = sc.resolve(sc.network.net_file).parent / "light.add.xml"
    df, stats = _run_section(sc, drv, (light,))
    after = df[df["time_s"] > GREEN_S]
    starts = after[after["speed_mps"] > 0.5].groupby("vehicle_id")["time_s"].min() - GREEN_S
    queued = df[(df["time_s"] == GREEN_S) & (df["speed_mps"] < 0.1)]["vehicle_id"]
    return starts.loc[sorted(queued)], stats


def test_a_reaction_time_starts_the_floored_queue_later(tmp_path: Path) -> None:
    """A queue that the floor alone starts (the policy always brakes): with one step each
    car moves off the step after its leader (0.5 s a car; drawn 528's policy 0.53 s, the
    truth's Krauss drivers 0.84-0.97 s); with SUMO's Krauss tau (1 s) the floor lifts it to
    half that speed, below 0.5 m/s at every other car's first step: 0.8 s a car; none
    collides or teleports."""
    lags = {}
    for reaction in (0.0, 1.0):
        starts, stats = queue_starts(_queue_scenario(tmp_path / str(reaction), reaction), 0)
        assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
        assert len(starts) >= 8, starts  # the queue stood
        lags[reaction] = starts.diff().dropna()
    assert (lags[0.0] == DT).all(), lags[0.0].tolist()
    assert lags[1.0].mean() >= 0.7, lags[1.0].tolist()
    assert (lags[1.0] >= DT).all(), lags[1.0].tolist()
