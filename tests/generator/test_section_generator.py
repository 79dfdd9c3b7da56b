"""Stage I on a section: gaps with open ends and lane drops, feasible completions, the macro
losses, training on a small budget, checkpoints.

Snapshots are synthetic (vehicles drawn per lane with spacings >= the minimum on real
SUMO section geometry: the Bremen motorway, whose edge E0 has a fourth lane, and the
paper's ring as a closed one-lane section), so no SUMO run is needed.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from ring_scenes import generator_scenario
from section_checks import lane_is_there

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_metrics import completion_metrics, completion_violations
from macromicro_sumo.generator.section_model import (
    SectionGeneratorNet,
    section_losses,
    spacings,
)
from macromicro_sumo.generator.section_sampler import (
    SectionCompletion,
    complete_section,
    uniform_completion,
)
from macromicro_sumo.generator.section_scene import Psi, Road, scene_gaps
from macromicro_sumo.generator.section_spread import speed_spread_target
from macromicro_sumo.generator.section_train import (
    _eval_loss,
    load_section_generator,
    save_section_generator,
    train_section_generator,
)
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.scenario.section import (
    SectionConfig,
)

ROOT = Path(__file__).resolve().parents[2]
S_MIN = 7.5
scenario = partial(generator_scenario, base={})  # the scenario's own defaults


@pytest.fixture(scope="module")
def ring() -> Section:
    return read_section(ROOT / "sumo_nets" / "ring_r100_e4.net.xml", ["e0", "e1", "e2", "e3"], True)


def synthetic(
    section: Section, n: int, seed: int, mean_gap_m: float = 150.0, p_obs: float = 0.2
) -> SectionSnapshots:
    """Scenes with per-lane spacings S_MIN + exponential, lane-dependent speeds, psi from the
    scene itself (mean speed, 1 / density, spacing std), k_est = k_true + noise."""
    rng = np.random.default_rng(seed)
    scenes = []
    for _ in range(n):
        lanes, arcs, speeds = [], [], []
        for lane in range(section.max_lanes):
            x = rng.uniform(0, 20)
            while x < section.length_m - (S_MIN if section.closed else 0.0):
                if lane_is_there(section, lane, x):
                    lanes.append(lane)
                    arcs.append(x)
                    speeds.append(rng.normal(25 + 3 * lane, 2.0))
                x += S_MIN + rng.exponential(mean_gap_m - S_MIN)
        scenes.append((np.array(lanes), np.array(arcs), np.array(speeds)))
    m = max(len(a) for _, a, _ in scenes)
    lane = np.zeros((n, m), np.int64)
    arc, speed = np.zeros((n, m)), np.zeros((n, m))
    valid, observed = np.zeros((n, m), bool), np.zeros((n, m), bool)
    psi = np.zeros((n, 6))
    for i, (ln, a, v) in enumerate(scenes):
        j = len(a)
        lane[i, :j], arc[i, :j], speed[i, :j], valid[i, :j] = ln, a, v, True
        observed[i, :j] = rng.random(j) < p_obs
        psi[i] = [v.mean(), section.lane_length_m / j, 0.0, 10.0, 45.0, S_MIN]
    snaps = SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 10.0,
        lane=lane,
        arc_m=arc,
        speed_mps=speed,
        length_m=np.full((n, m), 5.0),
        valid=valid,
        observed=observed,
        psi=psi,
        k_true=(valid & ~observed).sum(axis=1),
        k_est=np.maximum((valid & ~observed).sum(axis=1) + rng.integers(-3, 4, n), 0),
    )
    truth = SectionCompletion(lane, arc, speed, valid, valid & ~observed, psi[:, 0], psi[:, 0])
    psi[:, 2] = completion_metrics(section, snaps, truth, snaps.k_true)["true_std_spacing_m"]
    return snaps


def untrained(seed: int = 0) -> SectionGeneratorNet:
    torch.manual_seed(seed)
    return SectionGeneratorNet(32)


def check_completion(section: Section, snaps: SectionSnapshots, comp: SectionCompletion, k) -> None:
    """Independent of the module's own check: every pair along the lane connections
    (``section_leaders``) with a generated vehicle is >= S_MIN apart (around a loop too), speeds within psi's range,
    lanes present where they are (``lane_is_there``), observed vehicles untouched, K
    vehicles generated."""
    n = snaps.arc_m.shape[1]
    obs = snaps.valid & snaps.observed
    np.testing.assert_array_equal(comp.valid[:, :n], obs)
    np.testing.assert_array_equal(comp.arc_m[:, :n][obs], snaps.arc_m[obs])
    np.testing.assert_array_equal(comp.speed_mps[:, :n][obs], snaps.speed_mps[obs])
    np.testing.assert_array_equal(comp.generated.sum(axis=1), k)
    for i in range(len(snaps)):
        g = comp.generated[i]
        assert np.all(comp.arc_m[i, g] >= 0) and np.all(comp.arc_m[i, g] < section.length_m)
        v = comp.speed_mps[i, g]
        assert np.all(v >= snaps.psi[i, 3]) and np.all(v <= snaps.psi[i, 4])
        for ln, x in zip(comp.lane[i, g], comp.arc_m[i, g], strict=True):
            assert lane_is_there(section, int(ln), float(x)), (i, ln, x)
        # every pair along the lane connections (the environment's leaders)
        on = np.flatnonzero(comp.valid[i])
        leader, spacing = section_leaders(section, comp.lane[i, on], comp.arc_m[i, on])
        pair = leader >= 0
        touched = pair & (g[on] | g[on][np.maximum(leader, 0)])
        assert np.all(spacing[touched] >= S_MIN - 1e-6), (i, spacing[touched].min())


# --------------------------------------------------------------------------- geometry


def test_open_section_gaps_and_spacings(bremen: Section) -> None:
    """Open ends: the gap upstream of a lane's last vehicle and downstream of its first have
    one neighbour; an empty lane is one gap of the whole section; the first vehicle of a
    lane has no spacing (excluded from the losses)."""
    road = Road.of(bremen)
    lane = torch.tensor([[0, 0, 0, 1]])
    arc = torch.tensor([[10.0, 50.0, 100.0, 400.0]], dtype=torch.float64)
    present = torch.ones(1, 4, dtype=torch.bool)
    g = scene_gaps(lane, arc, torch.full((1, 4), 20.0), present, road, torch.tensor([S_MIN]), None)
    lanes = g.lane[0].tolist()
    rows = {
        (ln, round(float(s), 3)): j
        for j, (ln, s) in enumerate(zip(lanes, g.start[0].tolist(), strict=True))
    }
    head0 = rows[(0, 0.0)]  # upstream of the lane's last vehicle (arc 10)
    assert not g.has_f[0, head0] and g.has_l[0, head0]
    assert g.hi[0, head0] == pytest.approx(10.0 - S_MIN) and g.lo[0, head0] == 0.0
    down = rows[(0, 100.0)]  # downstream of the lane's first vehicle: open end
    assert g.has_f[0, down] and not g.has_l[0, down]
    assert g.length[0, down] == pytest.approx(bremen.length_m - 100.0)
    mid = rows[(0, 10.0)]
    assert g.lo[0, mid] == S_MIN and g.hi[0, mid] == pytest.approx(40.0 - S_MIN)
    empty = [j for j, ln in enumerate(lanes) if ln == 2 and bool(g.valid[0, j])]
    assert len(empty) == 1 and g.length[0, empty[0]] == pytest.approx(bremen.length_m)
    assert not g.has_f[0, empty[0]] and not g.has_l[0, empty[0]]
    sp, has = spacings(lane, arc, present, road)
    assert sorted(sp[has].tolist()) == pytest.approx([40.0, 50.0])  # 100 and 400 lead


def test_closed_section_wraps(ring: Section) -> None:
    road = Road.of(ring)
    lane = torch.zeros(1, 3, dtype=torch.long)
    arc = torch.tensor([[10.0, 200.0, 600.0]], dtype=torch.float64)
    sp, has = spacings(lane, arc, torch.ones(1, 3, dtype=torch.bool), road)
    assert has.all()
    assert sorted(sp[0].tolist()) == pytest.approx(sorted([190.0, 400.0, ring.length_m - 590.0]))


def test_losses_zero_for_a_scene_that_matches_psi(bremen: Section) -> None:
    """Equal spacings at psi's mean spacing, speeds at psi's mean: every term ~0; the
    leader-less vehicle's (unknown) spacing does not count."""
    road = Road.of(bremen)
    arc = torch.tensor([[100.0, 130.0, 160.0, 190.0]], dtype=torch.float64)
    lane = torch.zeros(1, 4, dtype=torch.long)
    psi = Psi.of(np.array([[20.0, 30.0, 0.0, 10.0, 30.0, S_MIN]]), np.array([0.0]))
    terms = section_losses(
        lane, arc, torch.full((1, 4), 20.0), torch.ones(1, 4, dtype=bool), psi, road
    )
    for name, v in terms.items():
        assert float(v[0]) < 1e-4, name
    psi_far = Psi.of(np.array([[20.0, 60.0, 10.0, 10.0, 30.0, 40.0]]), np.array([5.0]))
    far = section_losses(
        lane, arc, torch.full((1, 4), 25.0), torch.ones(1, 4, dtype=bool), psi_far, road
    )
    # psi has no upper spacing bound on a section: L_max is 0, every other term charges.
    assert float(far.pop("L_max")[0]) == 0.0
    assert all(float(v[0]) > 1e-3 for v in far.values())


def test_speed_spread_target_from_observed(bremen: Section) -> None:
    """Without a speed std in psi the observed vehicles' spread is the target; fewer than
    three observed: unknown (NaN), and L_vstd is then 0."""
    snaps = synthetic(bremen, 6, seed=5, p_obs=0.3)
    target = speed_spread_target(snaps)
    for i in range(len(snaps)):
        v = snaps.speed_mps[i][snaps.valid[i] & snaps.observed[i]]
        if len(v) >= 3:
            assert target[i] == pytest.approx(v.std(ddof=1))
        else:
            assert np.isnan(target[i])
    one = dataclasses.replace(snaps, observed=snaps.observed & (np.cumsum(snaps.observed, 1) <= 2))
    assert np.isnan(speed_spread_target(one)).all()


def test_positions_only_where_the_lane_exists(bremen: Section) -> None:
    """The lane added on the right of E0 (SUMO's lane 0 there; the through lanes shift up by
    one) is a lane of its own in the generator's numbering along the connections (3), on
    E0 alone: nothing on the section leads into it, so not in the junction before E0 either
    (that junction's lanes lead onto E0's through lanes, numbers 0-2). A point in a gap
    spanning the whole section lands on E0."""
    road = Road.of(bremen)
    e0 = bremen.edge_ids.index("E0")
    start = float(bremen.offsets_m[e0])
    assert road.lane_numbers(np.arange(4), np.full(4, start + 10.0)).tolist() == [3, 0, 1, 2]
    assert road.lane_numbers(np.array([3]), np.array([start - 1.0])).tolist() == [2]  # junction
    assert road.sumo_lanes(np.arange(4), np.full(4, start + 10.0)).tolist() == [1, 2, 3, 0]
    frac = torch.linspace(0.001, 0.999, 50, dtype=torch.float64)
    x = road.place_on_lane(
        torch.full((50,), 3), torch.zeros(50, dtype=torch.float64), torch.full((50,), 1800.0), frac
    )
    assert bremen.junction_m[e0 - 1] > 0
    assert np.all((x.numpy() >= start) & (x.numpy() < start + bremen.lengths_m[e0]))
    assert all(lane_is_there(bremen, 0, float(a)) for a in x)
    assert road.nearest_on_lane(3, 0.0, 500.0, 100.0) is None
    assert road.nearest_on_lane(3, 0.0, 1000.0, 100.0) == pytest.approx(start)


# --------------------------------------------------------------------------- completion


def test_completion_is_feasible_open_multilane(bremen: Section) -> None:
    snaps = synthetic(bremen, 24, seed=1)
    net = untrained()
    for k in (snaps.k_true, snaps.k_est):
        comp = complete_section(net, bremen, snaps, k, t_max=20, seed=3)
        check_completion(bremen, snaps, comp, k)
        assert comp.projections.sum() == 0
        assert np.all(comp.trials >= k)
        assert completion_violations(bremen, snaps, comp).to_numpy().sum() == 0
        # psi's mean speed is reachable in these scenes: the completion hits it exactly
        err = completion_metrics(bremen, snaps, comp, k)["speed_err_vs_psi_mps"]
        assert err.max() < 1e-9
    # the fourth lane (E0 only) receives vehicles, all on E0
    on3 = comp.generated & (comp.lane == 3)
    assert on3.sum() > 0


def test_completion_is_feasible_on_the_ring(ring: Section) -> None:
    snaps = synthetic(ring, 16, seed=2, mean_gap_m=40.0, p_obs=0.3)
    comp = complete_section(untrained(), ring, snaps, snaps.k_true, t_max=20, seed=0)
    check_completion(ring, snaps, comp, snaps.k_true)
    # a scene with no observed vehicle at all (the whole loop from a random anchor)
    none = dataclasses.replace(snaps, observed=np.zeros_like(snaps.observed))
    k = np.full(len(none), 6)
    comp = complete_section(untrained(), ring, none, k, t_max=20, seed=0)
    check_completion(ring, none, comp, k)


def test_overfull_section_projects_and_counts(ring: Section) -> None:
    """More vehicles than the loop holds at the minimum spacing (an over-estimated hidden
    count): placements without room are projected and counted, and a vehicle with no room
    anywhere is dropped and counted, never put onto its neighbours (an impossible scene)."""
    snaps = synthetic(ring, 2, seed=3, mean_gap_m=40.0)
    k = np.full(2, int(ring.length_m / S_MIN) + 10)
    comp = complete_section(untrained(), ring, snaps, k, t_max=5, seed=0)
    assert np.all(comp.generated.sum(axis=1) + comp.dropped == k)
    assert np.all(comp.projections > 0) and np.all(comp.dropped > 0)
    assert np.all(comp.trials <= 5 * k)
    for i in range(len(snaps)):
        for lane in np.unique(comp.lane[i][comp.valid[i]]):
            on = comp.valid[i] & (comp.lane[i] == lane)
            a = np.sort(comp.arc_m[i][on])
            gaps = np.append(np.diff(a), a[0] + ring.length_m - a[-1])
            assert gaps.min() >= 5.0, (i, lane, gaps.min())


def test_completion_is_deterministic_for_a_seed(bremen: Section) -> None:
    snaps = synthetic(bremen, 8, seed=4)
    net = untrained()
    a = complete_section(net, bremen, snaps, snaps.k_est, 20, seed=7)
    b = complete_section(net, bremen, snaps, snaps.k_est, 20, seed=7)
    c = complete_section(net, bremen, snaps, snaps.k_est, 20, seed=8)
    for f in ("lane", "arc_m", "speed_mps", "valid", "trials"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.arc_m, c.arc_m)


# --------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def trained(bremen: Section) -> tuple:
    sc = scenario(bremen, epochs=6, batch_size=16, hidden_size=32, k_source="truth", lr=1e-2)
    train, val = synthetic(bremen, 32, seed=10), synthetic(bremen, 16, seed=11)
    net, log = train_section_generator(sc, bremen, train, val, progress=False)
    before = _eval_loss(
        untrained(sc.seed), Road.of(bremen), val, val.k_true, sc.generator, sc.seed + 17
    )
    return net, log, sc, before


def test_training_lowers_the_macro_loss(trained) -> None:
    net, log, sc, before = trained
    assert list(log["epoch"]) == list(range(len(log)))
    assert {"train_loss", "val_loss", "val_L_var", "val_L_speed"} <= set(log.columns)
    assert log["val_loss"].min() < 0.7 * before["loss"]
    assert log["val_loss"].min() < log["val_loss"].iloc[0]


def test_generator_beats_uniform_on_mean_speed(trained, bremen: Section) -> None:
    net = trained[0]
    test = synthetic(bremen, 24, seed=12)
    gen = complete_section(net, bremen, test, test.k_true, 20, seed=0)
    uni = uniform_completion(None, bremen, test, test.k_true, 20, seed=0)
    check_completion(bremen, test, gen, test.k_true)
    m_gen = completion_metrics(bremen, test, gen, test.k_true)
    m_uni = completion_metrics(bremen, test, uni, test.k_true)
    assert m_gen["speed_err_vs_psi_mps"].mean() < 0.75 * m_uni["speed_err_vs_psi_mps"].mean()
    assert m_gen["feasible"].all() and not m_uni["feasible"].all()
    ratio = m_gen["std_spacing_m"].mean() / m_gen["true_std_spacing_m"].mean()
    assert 0.6 < ratio < 1.5


def test_checkpoint_round_trip_and_refusal(trained, bremen: Section, tmp_path: Path) -> None:
    net, _, sc, _ = trained
    path = tmp_path / "generator.pt"
    save_section_generator(path, net, sc, {"epoch": 3})
    back = load_section_generator(path, sc)
    snaps = synthetic(bremen, 4, seed=13)
    a = complete_section(net, bremen, snaps, snaps.k_true, 20, seed=1)
    b = complete_section(back, bremen, snaps, snaps.k_true, 20, seed=1)
    np.testing.assert_array_equal(a.arc_m, b.arc_m)
    other = dataclasses.replace(sc, section=SectionConfig(edges=["e0", "e1"], closed=True))
    with pytest.raises(UserError) as err:
        load_section_generator(path, other)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "section.edges" in msg
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match="corrupt"):
        load_section_generator(path, sc)


def test_safe_speeds_cap_generated_vehicles_behind_slow_leaders() -> None:
    """A generated vehicle 20 m/s faster than its leader 10 m ahead is capped to the speed it
    can still stop from; one in front of a fast observed follower is raised."""
    from macromicro_sumo.generator.section_sampler import SectionCompletion, safe_speeds

    ring = read_section(Path("sumo_nets/ring_r100_e4.net.xml"), ["e0", "e1", "e2", "e3"], True)
    comp = SectionCompletion(
        lane=np.zeros((1, 4), dtype=np.int64),
        arc_m=np.array([[100.0, 90.0, 300.0, 260.0]]),
        speed_mps=np.array([[10.0, 30.0, 5.0, 30.0]]),
        valid=np.ones((1, 4), dtype=bool),
        generated=np.array([[False, True, True, False]]),
        trials=np.zeros(1),
        projections=np.zeros(1),
    )
    safe_speeds(comp, ring, np.array([6.5]), 4.5)
    v = comp.speed_mps[0]
    assert v[1] == pytest.approx(np.sqrt(10.0**2 + 2 * 4.5 * (10.0 - 6.5)))
    assert v[2] == pytest.approx(np.sqrt(30.0**2 - 2 * 4.5 * (40.0 - 6.5)))
    assert v[0] == 10.0 and v[3] == 30.0  # observed vehicles keep their recorded speeds


def test_safe_speeds_deal_the_generated_speeds_out_again() -> None:
    """A generated vehicle too fast behind a slow one takes a slower generated speed that
    fits, and the one it took it from gets the fast one where that is safe: the scene's
    mean speed is kept where a cap alone would lower it."""
    from macromicro_sumo.generator.section_sampler import SectionCompletion, safe_speeds

    ring = read_section(Path("sumo_nets/ring_r100_e4.net.xml"), ["e0", "e1", "e2", "e3"], True)
    comp = SectionCompletion(
        lane=np.zeros((1, 3), dtype=np.int64),
        arc_m=np.array([[200.0, 190.0, 90.0]]),
        speed_mps=np.array([[10.0, 30.0, 10.0]]),
        valid=np.ones((1, 3), dtype=bool),
        generated=np.ones((1, 3), dtype=bool),
        trials=np.zeros(1),
        projections=np.zeros(1),
    )
    safe_speeds(comp, ring, np.array([6.5]), 4.5)
    np.testing.assert_allclose(comp.speed_mps[0], [10.0, 10.0, 30.0])


def kinematic_violations(
    section: Section, comp: SectionCompletion, s_min: float, b: float, tau: float
):
    """Pairs touching a generated vehicle whose follower cannot stop behind its leader
    (v_f^2 + 2 b tau v_f > v_l^2 + 2 b (spacing - s_min)), over all scenes."""
    from macromicro_sumo.road.leaders import section_leaders

    bad = 0
    for i in range(len(comp.valid)):
        on = np.flatnonzero(comp.valid[i])
        lead, sp = section_leaders(section, comp.lane[i, on], comp.arc_m[i, on])
        v, gen = comp.speed_mps[i, on], comp.generated[i, on]
        for f, j in enumerate(lead):
            if j >= 0 and (gen[f] or gen[j]):
                room = 2 * b * max(0.0, sp[f] - s_min)
                bad += v[f] ** 2 + 2 * b * tau * v[f] > v[j] ** 2 + room + 1e-6
    return bad


def test_generated_vehicles_only_where_both_neighbours_stay_consistent(ring: Section) -> None:
    """A platoon of observed vehicles 20 m apart at 15 m/s: each gap has room for a vehicle
    by the spacing bound, but no speed there lets both the follower stop behind it and it
    stop behind its leader. Positions are chosen where one does (the rest of the loop):
    every pair is kinematically consistent, where fixing speeds afterwards cannot be."""
    from macromicro_sumo.generator.section_sampler import safe_speeds

    n = 8
    arcs = np.array([100.0, 120, 140, 160, 180, 200])
    m = len(arcs)
    psi = np.tile([15.0, 40.0, 0.0, 0.0, 30.0, S_MIN], (n, 1))
    snaps = SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 10.0,
        lane=np.zeros((n, m), np.int64),
        arc_m=np.tile(arcs, (n, 1)),
        speed_mps=np.full((n, m), 15.0),
        length_m=np.full((n, m), 5.0),
        valid=np.ones((n, m), bool),
        observed=np.ones((n, m), bool),
        psi=psi,
        k_true=np.full(n, 8),
        k_est=np.full(n, 8),
    )
    b, tau = 4.5, 0.5
    comp = complete_section(
        untrained(), ring, snaps, snaps.k_true, 20, seed=0, brake_mps2=b, reaction_s=tau
    )
    check_completion(ring, snaps, comp, snaps.k_true)
    assert kinematic_violations(ring, comp, S_MIN, b, tau) == 0
    platoon = (comp.arc_m > 100.0) & (comp.arc_m < 200.0) & comp.generated
    assert not platoon.any()
    # Speeds alone: the same generator, positions by the spacing bound only.
    speeds_only = complete_section(untrained(), ring, snaps, snaps.k_true, 20, seed=0)
    safe_speeds(speeds_only, ring, psi[:, 5], b, tau)
    assert kinematic_violations(ring, speeds_only, S_MIN, b, tau) > 0
