"""``deploy.start_rules``: the vehicles the start rules (``deploy.start_dawdle``,
``deploy.start_reaction_s``) apply to. "signal_lanes": only those on a lane that can have a
signal ahead (``sumo.signal_reach.signal_lanes``), so that a queue at a light starts as
SUMO's drivers while a standing queue elsewhere (Bremen's merge queue, where the rules
lost 0.914 -> 0.964 m/s) starts as without them. Through ``speed_commands`` (numpy), then
real SUMO: a queue at a light starts late, a jam on a road without a signal is driven to
the bit as without the rules."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import line_net
from deploy_nets import queue_at_light, twelve_cars
from section_files import section_scenario
from test_floor_reaction import GREEN_S, queue_starts
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.population import DriveStats
from macromicro_sumo.deploy.safety import speed_commands
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario

DT = 0.5
RULES = {"start_dawdle": 0.5, "start_reaction_s": 1.0, "start_rules": "all"}
OFF = {"start_dawdle": 0.0, "start_reaction_s": 0.0}
GATED = {**RULES, "start_rules": "signal_lanes"}  # the defaults since stop 49


def test_speed_commands_apply_the_rules_where_named(tmp_path: Path) -> None:
    """Two standing cars 0.5 m behind leaders moving off at 1 m/s, the policy full
    throttle: with ``start_on`` [True, False] the first gets the rules' command (as with
    None: all), the second the command without the rules, to the bit; with none named
    both are as without the rules."""
    obs = np.zeros((2, 4))
    obs[:, 1] = 14.0  # own speed 0 (column 0), the limit, closing speed -1 (leader at 1)
    obs[:, 3] = -1.0
    gap, decel = np.full(2, 0.5), np.full(2, 4.5)

    def layer() -> tuple[np.ndarray, ...]:
        return gap, decel, decel, np.full(2, -1)

    def commands(deploy: dict, start_on: np.ndarray | None) -> np.ndarray:
        name = f"q{len(list(tmp_path.glob('q*.toml')))}"  # a fresh scenario file each call
        sc = load_scenario(queue_at_light(tmp_path / f"{name}.toml", GREEN_S, deploy))
        act = lambda o: np.full(len(o), 2.6)  # noqa: E731
        args = (sc, act, "sumo", DriveStats(), obs, layer)
        return speed_commands(*args, vmax=np.inf, accel=2.6, start_on=start_on)

    off = commands(OFF, None)
    on_all = commands(RULES, None)
    assert on_all[0] < 0.9 * off[0]  # the rules start it later
    mixed = commands(RULES, np.array([True, False]))
    assert mixed[0] == on_all[0] and mixed[1] == off[1]
    np.testing.assert_array_equal(commands(RULES, np.zeros(2, bool)), off)
    # Gated and nobody named (a caller that knows no lanes): as without the rules.
    np.testing.assert_array_equal(commands(GATED, None), off)


def _jam_scenario(folder: Path, deploy: dict) -> Path:
    """A (400 m) -> B (200 m), one lane at 14 m/s, no signal; 12 cars 2 s apart. The
    policy (``_JamPolicy``) stands the first car from 10 s to 40 s: a queue behind it on a
    road without a signal ahead. The floor off, so that the standing car stays."""
    net_dir = folder / "net"
    net_dir.mkdir(parents=True)
    net = line_net(net_dir, (400.0, 600.0), 1, 14.0)
    routes = net_dir / "jam.rou.xml"
    routes.write_text(twelve_cars())
    return section_scenario(
        folder / "jam.toml",
        net,
        routes,
        ["A", "B"],
        seed=3,
        penetration=0.01,
        simulation={"warmup_s": 0.0, "duration_s": 80.0, "n_runs": 1},
        detectors={"interval_s": 30.0},
        deploy={"safety_floor_share": 0.0, **deploy},
    )


class _JamPolicy:
    """Toward the limit at up to 2.6 m/s^2; the car with nobody ahead brakes at 4.5 m/s^2
    from step 20 to step 79 (10-40 s), so that it stands and a queue forms behind it."""

    def __init__(self) -> None:
        self.step = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        a = np.clip((obs[:, 1] - obs[:, 0]) / DT, -4.5, 2.6)
        if 20 <= self.step < 80:
            a[obs[:, 2] > 200.0] = -4.5  # nobody ahead: NO_LEADER_GAP_M
        self.step += 1
        return a


def _jam_run(toml: Path) -> tuple[pd.DataFrame, dict]:
    sc = load_scenario(toml)
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B"], False)
    return _run_section(sc, SectionSpeedDriver(sc, section, 0, _JamPolicy(), "sumo"))


def _lags(df: pd.DataFrame, at_s: float) -> pd.Series:
    """The start lag of each car standing at ``at_s`` behind the one ahead (its first step
    above 0.5 m/s after ``at_s``), in queue order."""
    after = df[df["time_s"] > at_s]
    starts = after[after["speed_mps"] > 0.5].groupby("vehicle_id")["time_s"].min()
    queued = df[(df["time_s"] == at_s) & (df["speed_mps"] < 0.1)]["vehicle_id"]
    return starts.loc[sorted(queued)].diff().dropna()


def test_a_jam_without_a_signal_ahead_is_left_as_without_the_rules(tmp_path: Path) -> None:
    """The jam on the road without a signal: with the rules on all it starts later (about
    0.8 s a car against a step); with them on the signal lanes alone its trajectories are
    those without the rules, to the bit. None collides or teleports."""
    runs = {}
    for name, deploy in (
        ("off", OFF),
        ("all", RULES),
        ("gated", GATED),
    ):
        runs[name] = _jam_run(_jam_scenario(tmp_path / name, deploy))
        stats = runs[name][1]
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (name, stats)
    off = _lags(runs["off"][0], 40.0)
    assert len(off) >= 7, off  # the queue stood
    assert (off == DT).all(), off.tolist()
    assert _lags(runs["all"][0], 40.0).mean() >= 0.7
    pd.testing.assert_frame_equal(runs["gated"][0], runs["off"][0])


def test_a_queue_at_a_light_starts_late_with_the_gate(tmp_path: Path) -> None:
    """The queue at a real SUMO light stands on a signal lane: with the rules gated to
    those it starts as late as with them on all (about 0.8 s a car, never sooner than a
    step); without a collision."""
    starts, stats = queue_starts(queue_at_light(tmp_path / "q.toml", GREEN_S, GATED), 1)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, stats
    lags = starts.diff().dropna()
    assert len(lags) >= 7 and lags.mean() >= 0.7 and (lags >= DT).all(), lags.tolist()


def test_an_unknown_gate_is_refused(tmp_path: Path) -> None:
    """A value outside the choices is a one-line error naming the field."""
    with pytest.raises(UserError, match="start_rules"):
        load_scenario(queue_at_light(tmp_path / "x.toml", GREEN_S, {"start_rules": "some"}))
