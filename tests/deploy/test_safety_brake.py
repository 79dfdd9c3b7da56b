"""``deploy.safety_brake``: the braking the safety layer plans a driven vehicle's stop
with (``deploy.brake_plan.planned_decel``). "own" (its vType's decel) holds an IDM car behind
a Krauss car to gaps SUMO's own IDM does not keep, since IDM's decel is its comfortable
braking; "matched" (at least the leader's) does not, and still keeps every gap >= 0, in
numpy and in real SUMO against adversarial commands."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from deploy_nets import CAR, merge_net
from section_files import routes_file, section_scenario
from test_safety import _run_section, adversary

from macromicro_sumo.deploy.brake_plan import SAFETY_BRAKES, planned_decel
from macromicro_sumo.deploy.drivers import SectionSpeedDriver
from macromicro_sumo.deploy.observe import STOP_DECEL_MPS2
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.physics import safe_speed
from macromicro_sumo.road.section import read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section

# SUMO's IDM with its decel (comfortable braking) below the Krauss car's 4.5 m/s^2, as
# the drawn networks' car_idm.
CAR_IDM = (
    '<vType id="car_idm" length="4.5" minGap="2.0" carFollowModel="IDM" accel="1.5" '
    'decel="3.0" tau="1.2" speedDev="0.1"/>'
)
DECEL = {"car": 4.5, "car_idm": 3.0}


def _mixed_merge(folder: Path, brake: str) -> Path:
    """The merge (``deploy_nets.merge_net``) with a fleet of Krauss cars and IDM cars
    (half each, 3,300 veh/h), 5% instrumented, one run of 30 + 150 s."""
    net, _ = merge_net(folder / "net")
    flow = 'type="mix" begin="0" end="3600" departLane="best" departSpeed="max"'
    routes = routes_file(
        folder / "net" / "mixed.rou.xml",
        [CAR, CAR_IDM, '<vTypeDistribution id="mix" vTypes="car car_idm" probabilities="0.5 0.5"/>'],
        [f'<flow id="m" route="main" vehsPerHour="2800" {flow}/>',
         f'<flow id="r" route="ramp" vehsPerHour="500" {flow}/>'],
        ['<route id="main" edges="A B C"/>', '<route id="ramp" edges="R B C"/>'],
    )  # fmt: skip
    return section_scenario(
        folder / f"mixed_{brake}.toml",
        net,
        routes,
        ["A", "B", "C"],
        name="mixed_merge",
        seed=7,
        penetration=0.05,
        simulation={"warmup_s": 30.0, "duration_s": 150.0, "n_runs": 1},
        detectors={"interval_s": 30.0, "auto_spacing_m": 300.0},
        policy={"observation": "lookahead"},
        deploy={"safety_brake": brake},
    )


def _min_gap_after(v, gap, v_l, b, b_l, dt, steps: int = 200) -> np.ndarray:
    """The smallest bumper gap at any step end [m]: the follower one step at ``v``, then
    braking at ``b``; the leader braking at ``b_l`` from now (Euler, as SUMO moves both)."""
    k = np.arange(1, steps + 1)[:, None]
    follower = np.maximum(v - b * dt * (k - 1), 0.0)
    leader = np.maximum(v_l - b_l * dt * k, 0.0)
    return (np.maximum(gap, 0.0) + np.cumsum(leader - follower, axis=0) * dt).min(axis=0)


def test_matched_plans_no_softer_than_own_and_keeps_every_gap() -> None:
    """Over seeded random states: "matched" is the vType's decel where the leader brakes
    no harder, or where it is a standing obstacle (``STOP_DECEL_MPS2``), and the leader's
    otherwise; its safe speed is never below "own"'s, higher behind a harder-braking
    leader; and a follower at it, braking at the planned decel after one step, keeps a
    gap >= 0 at every step behind a leader that brakes at its decel (not only where the
    two stop)."""
    rng = np.random.default_rng(29)
    n, dt = 4000, 0.5
    b = rng.choice([1.5, 3.0, 4.0, 4.5], n)
    b_l = np.where(rng.random(n) < 0.1, STOP_DECEL_MPS2, rng.choice([1.5, 3.0, 4.0, 4.5], n))
    v_l = np.where(b_l == STOP_DECEL_MPS2, 0.0, rng.uniform(0.0, 35.0, n))
    gap = rng.uniform(0.0, 120.0, n)
    own, matched = planned_decel(b, b_l, "own"), planned_decel(b, b_l, "matched")
    np.testing.assert_array_equal(own, b)
    moving = b_l < STOP_DECEL_MPS2
    np.testing.assert_array_equal(matched, np.where(moving, np.maximum(b, b_l), b))
    safe_own = safe_speed(gap, v_l, own, b_l, dt)
    safe_matched = safe_speed(gap, v_l, matched, b_l, dt)
    assert np.all(safe_matched >= safe_own - 1e-12)
    harder = moving & (b_l > b) & (gap > 5.0)
    assert np.all(safe_matched[harder] > safe_own[harder] + 0.1)
    for brake, safe in (("own", safe_own), ("matched", safe_matched)):
        low = _min_gap_after(safe, gap, v_l, planned_decel(b, b_l, brake), b_l, dt)
        assert low.min() >= -1e-9, (brake, low.min())


def _truth_lowered(folder: Path) -> dict[str, pd.Series]:
    """Per ``deploy.safety_brake`` and follower vType, the share of SUMO's own next speeds
    of a car behind a Krauss car above the layer's safe speed (the ground truth, nobody
    driven: one simulation serves both)."""
    sc = load_scenario(_mixed_merge(folder, "own"))
    gt = simulate_section(sc, folder / "gt", progress=False)
    tr = pd.read_csv(gt / "trajectories.csv")
    vt = pd.read_csv(gt / "vtypes.csv").set_index("vtype")
    section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
    dt = sc.simulation.step_length_s
    nxt = tr.set_index(["vehicle_id", "time_s"])["speed_mps"]
    rows = []
    for t, s in tr.groupby("time_s"):
        lead, spacing = section_leaders(section, s["lane_index"].to_numpy(), s["arc_m"].to_numpy())
        ok = lead >= 0
        f, ld = s[ok], s.iloc[lead[ok]]
        ok_l = (ld["vtype"] == "car").to_numpy()
        f, ld = f[ok_l], ld[ok_l]
        gap = (
            spacing[ok][ok_l]
            - vt.loc[ld["vtype"], "length_m"].to_numpy()
            - vt.loc[f["vtype"], "min_gap_m"].to_numpy()
        )
        b = f["vtype"].map(DECEL).to_numpy()
        b_l = np.full(len(f), DECEL["car"])
        later = [nxt.get((v, round(t + dt, 6)), np.nan) for v in f["vehicle_id"]]
        row = {"vtype": f["vtype"].to_numpy(), "later": later}
        for brake in SAFETY_BRAKES:
            b_plan = planned_decel(b, b_l, brake)
            row[brake] = safe_speed(gap, ld["speed_mps"].to_numpy(), b_plan, b_l, dt)
        rows.append(pd.DataFrame(row))
    df = pd.concat(rows).dropna()
    return {
        brake: (df["later"] > df[brake] + 0.01).groupby(df["vtype"]).mean()
        for brake in SAFETY_BRAKES
    }


def test_own_braking_is_stricter_than_sumos_idm_and_matched_is_not(tmp_path: Path) -> None:
    """SUMO's own cars behind Krauss cars on the merge: the layer with "own" would lower
    a share of the IDM cars' next speeds (it plans their stop at 3.0 m/s^2 behind a
    leader's at 4.5), none of the Krauss cars' (their tau of 1 s asks more than the
    layer's one step); with "matched", next to none of either."""
    shares = _truth_lowered(tmp_path)
    own, matched = shares["own"], shares["matched"]
    assert own["car_idm"] > 0.05, own
    assert matched["car_idm"] < 0.2 * own["car_idm"], (own, matched)
    assert own["car"] < 0.002 and matched["car"] < 0.002, (own, matched)


@pytest.mark.parametrize("kind", ["full", "random"])
def test_matched_braking_lets_no_command_collide(tmp_path: Path, kind: str) -> None:
    """The mixed fleet on the merge, every hidden car driven at full throttle or random
    accelerations in [-4.5, 2.6] m/s^2 (seeded): with "matched" no collision and no
    teleport; at full throttle the driven IDM cars follow Krauss cars closer than with
    "own" (the layer alone sets that gap), and both keep them moving."""
    headway = {}
    for brake in ("own", "matched") if kind == "full" else ("matched",):
        sc = load_scenario(_mixed_merge(tmp_path / brake, brake))
        section = read_section(sc.resolve(sc.network.net_file), ["A", "B", "C"], False)
        act = adversary(kind, *sc.bounds.accel_mps2, seed=3)
        drv = SectionSpeedDriver(sc, section, 0, act, "sumo")
        df, stats = _run_section(sc, drv)
        assert stats["collisions"] == 0 and stats["teleports"] == 0, (brake, stats)
        assert drv.stats.vehicle_steps_driven > 2000
        hw = []
        for _, s in df.groupby("time_s"):
            lead, spacing = section_leaders(
                section, s["lane_index"].to_numpy(), s["arc_m"].to_numpy()
            )
            ok = lead >= 0
            f, ld = s[ok], s.iloc[lead[ok]]
            sel = (
                (f["vtype"] == "car_idm").to_numpy()
                & ~f["observed"].to_numpy()
                & (ld["vtype"] == "car").to_numpy()
                & (f["speed_mps"] > 15.0).to_numpy()
            )
            hw.append(spacing[ok][sel] / f["speed_mps"].to_numpy()[sel])
        # The closest following (10th percentile of the time headways above 15 m/s).
        headway[brake] = float(np.percentile(np.concatenate(hw), 10))
        assert df.loc[~df["observed"], "speed_mps"].mean() > 5.0  # the floor: 6 m/s
    if kind == "full":
        assert headway["matched"] < 0.7 * headway["own"], headway
