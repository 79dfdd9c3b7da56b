"""``deploy.command_dawdle = "auto"``: SUMO's default dawdle (sigma 0.5) only on the vehicles
whose policy's Krauss prior's a exceeds their vType's dawdled mean a (1 - 0.5 / 2), off
elsewhere and without a Krauss prior (``deploy.safety.auto_dawdled_accel``): the rule
(numpy), the setting's file checks, the action batch's prior a (``deploy.policy_batch``) and
a queue at a real SUMO light driven by a Krauss prior, the same to the bit as 0 or 0.5."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from conftest import CROSS_KRAUSS, ROOT, prior_alone
from deploy_nets import sparse_merge
from test_command_dawdle import _queue
from test_safety import _run_section

from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.run import sampled
from macromicro_sumo.deploy.safety import auto_dawdled_accel, dawdled_accel
from macromicro_sumo.errors import UserError
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario

V = np.array([0.0, 1.0, 2.6, 10.0])


def test_auto_is_off_below_the_dawdled_mean_and_on_above() -> None:
    """A prior's a of 1.80 (Bremen's fit) is below a car's 2.6 x 0.75 = 1.95: off, ``accel``
    itself; the fallback 2.6 is above: ``dawdled_accel`` at 0.5, equal to the bit; per
    vehicle, a truck's 1.3 (dawdled 0.975) is on under 1.5 where the car beside it is off;
    no Krauss prior (None): off."""
    assert auto_dawdled_accel(2.6, V, 1.80) == 2.6
    assert auto_dawdled_accel(2.6, V, None) == 2.6
    np.testing.assert_array_equal(auto_dawdled_accel(2.6, V, 2.6), dawdled_accel(2.6, V, 0.5))
    cars = np.full(4, 2.6)
    assert auto_dawdled_accel(cars, V, 1.80) is cars
    accel = np.array([2.6, 1.3, 2.6, 1.3])
    got = auto_dawdled_accel(accel, V, 1.5)
    want = np.where([False, True, False, True], dawdled_accel(accel, V, 0.5), accel)
    np.testing.assert_array_equal(got, want)
    assert got[1] < 1.3 and got[0] == 2.6  # the truck dawdles, the car does not
    # The edge: a prior's a equal to the dawdled mean dawdles no further (off).
    assert auto_dawdled_accel(2.6, V, 1.95) == 2.6


def test_the_setting_loads_auto_and_refuses_other_words_in_one_line(tmp_path: Path) -> None:
    """The values "auto", "signals", 0 and 0.5 load; "often", 1.5 and true are refused, each in one line naming the
    file, the field and the accepted values; 0 is left out of the digest (the scenarios that
    do not set it keep theirs), "auto" is not."""
    assert load_scenario(_queue(tmp_path / "a", "auto")).deploy.command_dawdle == "auto"
    assert load_scenario(_queue(tmp_path / "s", "signals")).deploy.command_dawdle == "signals"
    off = load_scenario(_queue(tmp_path / "o", 0.0))
    assert off.deploy.command_dawdle == 0.0 and "command_dawdle" not in off.to_dict()["deploy"]
    auto = load_scenario(_queue(tmp_path / "b", "auto"))
    assert auto.to_dict()["deploy"]["command_dawdle"] == "auto"
    for bad in ("often", 1.5, True):
        path = _queue(tmp_path / f"bad_{bad}", bad)
        with pytest.raises(UserError) as err:
            load_scenario(path)
        msg = str(err.value)
        assert "\n" not in msg and str(path) in msg and "deploy.command_dawdle" in msg, msg
        assert "[0, 1]" in msg and "'auto'" in msg and "'signals'" in msg, msg


@pytest.mark.parametrize(("prior", "want"), [("krauss", 2.6), ("idm", None), ("none", None)])
def test_the_action_batch_carries_a_krauss_priors_a_only(prior: str, want: float | None) -> None:
    """A Krauss prior's a travels with its action batch (and its sampled twin); an IDM prior
    (its a is not a Krauss mean's) and no prior carry None: auto is off for them."""
    params = dict(CROSS_KRAUSS)
    if prior == "idm":
        params = {
            "speed_factor": 1.0,
            "tau_s": 1.2,
            "accel_mps2": 2.6,
            "decel_mps2": 4.5,
            "min_gap_m": 2.5,
            "delta": 4.0,
            "veh_length_m": 5.0,
        }
    act = prior_alone(params, prior) if prior != "none" else prior_alone({}, "none")
    got = act.prior_accel_mps2
    assert got == (pytest.approx(want) if want is not None else None)
    draw = sampled(act, 0.3, np.random.default_rng(0))
    assert draw.prior_accel_mps2 == act.prior_accel_mps2


def _deploy(tmp_path: Path, sigma: float | str, prior_accel: float, merge: bool = False):
    """The queue of ``test_command_dawdle`` (``merge``: ``sparse_merge``, a network without
    traffic lights) driven by the Krauss prior alone (a = ``prior_accel``) at
    ``deploy.command_dawdle = sigma``: its trajectories and counts."""
    folder = tmp_path / f"{sigma}_{prior_accel}_{merge}"
    if merge:
        sc = load_scenario(sparse_merge(folder, deploy={"command_dawdle": sigma}))
        edges, extra = ["A", "B", "C"], ()
    else:
        sc = load_scenario(_queue(folder, sigma))
        edges, extra = ["A", "B"], (sc.resolve(sc.network.net_file).parent / "light.add.xml",)
    section = read_section(sc.resolve(sc.network.net_file), edges, False)
    act = prior_alone({**CROSS_KRAUSS, "accel_mps2": prior_accel, "dt_s": 0.5})
    drv = SectionSpeedDriver(sc, section, 0, act, "sumo")
    df, stats = _run_section(sc, drv, extra)
    assert stats["collisions"] == 0 and stats["teleports"] == 0, (sigma, stats)
    return df.drop(columns=[c for c in df.columns if "source" in c]), stats


def test_auto_deploys_as_off_under_a_fitted_prior_and_as_half_under_a_fallback(
    tmp_path: Path,
) -> None:
    """In real SUMO, a queue at a light discharged by a Krauss prior: auto with the prior's a
    at 1.80 (fitted, below 1.95) drives the same trajectories to the bit as 0; at 2.6 (the
    fallback) the same as 0.5. Under either prior 0 and 0.5 differ (at 1.80 through the
    floor's capped reach), so auto chose. "signals" is auto here: the queue has a light."""
    got = {}
    runs = (("auto", 1.80), (0.0, 1.80), (0.5, 1.80), ("auto", 2.6), (0.5, 2.6), (0.0, 2.6))
    runs += (("signals", 1.80), ("signals", 2.6))
    for sigma, a in runs:
        got[sigma, a] = _deploy(tmp_path, sigma, a)
    for (sigma, a), same in {("auto", 1.80): 0.0, ("auto", 2.6): 0.5, ("signals", 1.80): 0.0,
                             ("signals", 2.6): 0.5}.items():  # fmt: skip
        df, stats = got[sigma, a]
        want_df, want_stats = got[same, a]
        assert df.equals(want_df), (sigma, a)
        for key, value in stats.items():
            other = want_stats[key]
            same_value = value.equals(other) if hasattr(value, "equals") else value == other
            assert same_value, (sigma, a, key)
    # 0 and 0.5 differ under either prior (0.5 caps the floor's reach at 1.80 too): auto
    # chose between two different deployments.
    for a in (1.80, 2.6):
        assert not got[0.5, a][0].equals(got[0.0, a][0]), a


def test_deploy_runs_sets_auto_or_a_number(tmp_path: Path) -> None:
    """``scripts/deploy_runs.py --set deploy.command_dawdle=auto`` sets the word, ``=0.5``
    the number (a float, as the file's), where the field is a number by default."""
    spec = importlib.util.spec_from_file_location(
        "deploy_runs", ROOT / "scripts" / "deploy_runs.py"
    )
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    sc = load_scenario(_queue(tmp_path, 0.0))
    assert script.changed(sc, ["deploy.command_dawdle=auto"]).deploy.command_dawdle == "auto"
    half = script.changed(sc, ["deploy.command_dawdle=0.5"]).deploy.command_dawdle
    assert half == 0.5 and isinstance(half, float)


def test_signals_is_off_on_a_network_without_traffic_lights(tmp_path: Path) -> None:
    """On a merge without traffic lights, driven by a fallback prior (a 2.6): "signals" drives
    the same trajectories to the bit as 0, where "auto" (the same as 0.5) differs."""
    off = _deploy(tmp_path, 0.0, 2.6, merge=True)[0]
    assert _deploy(tmp_path, "signals", 2.6, merge=True)[0].equals(off)
    assert not _deploy(tmp_path, "auto", 2.6, merge=True)[0].equals(off)
