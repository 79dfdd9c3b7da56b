"""L_pair (``generator.lambda_pair``): spacing and leader-speed difference of each pair, the
recorded pairs' correlation as the target, and a term that trains speeds towards it."""

from __future__ import annotations

import math

import numpy as np
import torch
from ring_scenes import loop_snapshots
from test_section_spread import completed

from macromicro_sumo.generator.pair_dynamics import (
    SLOPE_SCALE,
    pair_states,
    pair_term,
    pooled_slope,
    recorded_pair_slope,
)
from macromicro_sumo.generator.section_scene import Road
from macromicro_sumo.road.section import Section


def test_pairs_follow_the_loop(ring_loop: Section) -> None:
    """Each vehicle's spacing and dv are to the next one ahead, the last one's around the loop."""
    length = ring_loop.length_m
    arc = torch.tensor([[300.0, 10.0, 150.0]], dtype=torch.float64)
    speed = torch.tensor([[13.0, 11.0, 12.0]], dtype=torch.float64)
    present = torch.ones(1, 3, dtype=torch.bool)
    lane = torch.zeros(1, 3, dtype=torch.long)
    sp, dv, counts, order, lead = pair_states(lane, arc, speed, present, Road.of(ring_loop))
    assert order.tolist() == [[1, 2, 0]] and lead.tolist() == [[2, 0, 1]]
    np.testing.assert_allclose(sp[0].numpy(), [140.0, 150.0, length - 290.0])
    np.testing.assert_allclose(dv[0].numpy(), [1.0, 1.0, -2.0])
    assert counts.all()


def test_pooled_slope_is_least_squares() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=200), rng.normal(size=200)
    y = y + 0.5 * x
    w = rng.random(200) < 0.7
    got = pooled_slope(torch.as_tensor(x), torch.as_tensor(y), torch.as_tensor(w))
    assert math.isclose(float(got), np.polyfit(x[w], y[w], 1)[0], rel_tol=1e-9)
    assert math.isnan(float(pooled_slope(torch.zeros(2), torch.zeros(2), torch.ones(2))))


def _scenes_with_correlation(section: Section, n: int, slope: float, seed: int):
    """``n`` five-car loops whose speeds are set so that v_leader - v = slope x (spacing - mean)
    + noise: a known positive correlation of spacing and dv."""
    rng = np.random.default_rng(seed)
    length = section.length_m
    arc, speed = np.zeros((n, 5)), np.zeros((n, 5))
    for i in range(n):
        gaps = 60.0 + rng.dirichlet(np.full(5, 7.0)) * (length - 300.0)
        arc[i] = np.concatenate([[0.0], np.cumsum(gaps[:-1])])
        dv = slope * (gaps - gaps.mean()) + rng.normal(0, 0.2, 5)
        dv -= dv.mean()  # around the loop the differences sum to 0
        # v[j + 1] - v[j] = dv[j]: integrate along the loop
        speed[i] = 12.0 + np.concatenate([[0.0], np.cumsum(dv[:-1])])
    observed = np.ones((n, 5), bool)
    psi = np.tile([12.0, length / 5, 30.0, 10.0, 14.0, 7.0], (n, 1))
    return loop_snapshots(arc, speed, observed, psi)


def test_the_target_is_the_recorded_pairs_slope(ring_loop: Section) -> None:
    road = Road.of(ring_loop)
    snaps = _scenes_with_correlation(ring_loop, 60, 0.02, 1)
    full = recorded_pair_slope(snaps, snaps.valid, road)
    assert 0.01 < full < 0.03  # the slope the scenes were drawn with, within noise
    # Only pairs with both ends recorded count: with one car unrecorded per scene, the pairs
    # through it are left out and the estimate moves, but stays near the drawn slope.
    rec = snaps.valid.copy()
    rec[:, 2] = False
    part = recorded_pair_slope(snaps, rec, road)
    assert part != full and 0.01 < part < 0.03
    # Too few pairs: no target.
    assert math.isnan(recorded_pair_slope(snaps.take(np.arange(3)), snaps.valid[:3], road))


def _speed_var(scene) -> torch.Tensor:
    w = scene.present.double()
    m = (w * scene.speed).sum(1) / w.sum(1)
    return (w * (scene.speed - m[:, None]) ** 2).sum(1) / (w.sum(1) - 1)  # sample variance


def test_the_term_is_zero_at_its_targets_and_trains_the_speeds(ring_loop: Section) -> None:
    """Zero where the batch already has the target slope and speed spread, one per
    SLOPE_SCALE off; its gradient reaches the generated speeds; 0 without a target."""
    scene, _, road, _ = completed(ring_loop, 60, 2)
    one = scene.k == 2
    sub = (scene.lane[one], scene.arc[one], scene.speed[one], scene.present[one], scene.k[one])
    sp, dv, counts, _, _ = pair_states(*sub[:4], road, scene.n_obs_slots)
    slope = float(pooled_slope(sp, dv, counts))
    var = _speed_var(scene)[one]
    same_spread = torch.full_like(var, float(var.mean().sqrt()))
    assert float(pair_term(*sub, road, scene.n_obs_slots, slope, same_spread)) < 1e-20
    # Off in slope by one SLOPE_SCALE: 1; and a spread off by a factor adds its squared error.
    off = pair_term(*sub, road, scene.n_obs_slots, slope + SLOPE_SCALE, same_spread)
    assert math.isclose(float(off), 1.0, rel_tol=1e-9)
    wide = pair_term(*sub, road, scene.n_obs_slots, slope, same_spread * math.sqrt(2.0))
    assert math.isclose(float(wide), 0.25, rel_tol=1e-9)
    # A scene without a spread target takes the others' mean: the same 0.25.
    part = (same_spread * math.sqrt(2.0)).clone()
    part[::2] = math.nan
    gap = pair_term(*sub, road, scene.n_obs_slots, slope, part)
    assert math.isclose(float(gap), 0.25, rel_tol=1e-9)

    speed = scene.speed.clone().requires_grad_(True)
    spread = torch.full((len(speed),), math.nan, dtype=torch.float64)
    args = (scene.lane, scene.arc.detach(), speed, scene.present, scene.k, road, scene.n_obs_slots)
    here = pair_term(*args, target=0.0, speed_std=spread)
    here.backward()
    assert float(here.detach()) > 0 and speed.grad is not None
    assert float(speed.grad[:, scene.n_obs_slots :].abs().sum()) > 0
    assert float(pair_term(*args, target=math.nan, speed_std=spread)) == 0.0
