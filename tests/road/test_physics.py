"""Pure physics and loss terms, tested without SUMO."""

from __future__ import annotations

import math

import numpy as np
import pytest
from loss_terms import spacing_losses, speed_loss
from ring_reference import ring_leaders, sorted_spacings

from macromicro_sumo.road.physics import brake_gap, idm_accel, safe_speed

L = 2 * math.pi * 100.0  # the paper's ring [m]

# One heterogeneous-free IDM driver [SI units].
IDM = dict(desired_speed_mps=13.0, tau_s=1.2, accel_mps2=1.0, decel_mps2=1.5, min_gap_m=2.0)


def accel(speed, gap, delta_v, **over):
    p = {**IDM, **over}
    return idm_accel(
        np.asarray(speed, float),
        np.asarray(gap, float),
        np.asarray(delta_v, float),
        p["desired_speed_mps"],
        p["tau_s"],
        p["accel_mps2"],
        p["decel_mps2"],
        p["min_gap_m"],
    )


# --------------------------------------------------------------------------- ring geometry


def test_spacings_sum_to_ring_length():
    arc = np.random.default_rng(0).uniform(0, L, (50, 7))
    _, spacing = ring_leaders(arc, L)
    np.testing.assert_allclose(spacing.sum(-1), L, rtol=0, atol=1e-9)
    assert (spacing > 0).all()
    np.testing.assert_allclose(sorted_spacings(arc, L).sum(-1), L, rtol=0, atol=1e-9)


def test_leader_is_next_in_arc_order_with_wrap_around():
    arc = np.array([10.0, 300.0, 600.0, 50.0])
    leader, spacing = ring_leaders(arc, L)
    # Arc order 0 -> 3 -> 1 -> 2 -> (wrap) 0.
    assert leader.tolist() == [3, 2, 0, 1]
    np.testing.assert_allclose(spacing, [40.0, 300.0, L - 600.0 + 10.0, 250.0], atol=1e-9)


def test_positions_outside_one_lap_are_wrapped():
    arc = np.array([10.0, 300.0, 600.0, 50.0])
    shifted = arc + np.array([0.0, -1.0, 2.0, 1.0]) * L
    leader, spacing = ring_leaders(shifted, L)
    leader0, spacing0 = ring_leaders(arc, L)
    assert leader.tolist() == leader0.tolist()
    np.testing.assert_allclose(spacing, spacing0, atol=1e-9)


def test_batched_leaders_equal_ring_by_ring():
    arc = np.random.default_rng(1).uniform(0, L, (3, 4, 6))
    leader, spacing = ring_leaders(arc, L)
    assert leader.shape == spacing.shape == (3, 4, 6)
    for i in range(3):
        for j in range(4):
            li, si = ring_leaders(arc[i, j], L)
            assert leader[i, j].tolist() == li.tolist()
            np.testing.assert_array_equal(spacing[i, j], si)


# --------------------------------------------------------------------------- IDM


def test_free_road_accelerates_toward_desired_speed():
    v0 = IDM["desired_speed_mps"]
    assert accel(5.0, 1e6, 0.0) == pytest.approx(IDM["accel_mps2"] * (1 - (5 / v0) ** 4))
    assert accel(v0, 1e6, 0.0) == pytest.approx(0.0, abs=1e-9)
    assert accel(v0 + 2, 1e6, 0.0) < 0
    # Euler from standstill: speed rises monotonically to v0 and never overshoots.
    v, dt, trace = 0.0, 0.1, []
    for _ in range(1200):
        v = max(0.0, v + float(accel(v, 1e6, 0.0)) * dt)
        trace.append(v)
    assert np.all(np.diff(trace) >= 0)
    assert max(trace) <= v0
    assert trace[-1] == pytest.approx(v0, abs=0.05)


def test_stopped_leader_makes_follower_brake_and_stop_before_it():
    assert accel(15.0, 30.0, 15.0) < -IDM["decel_mps2"]  # closing fast: brakes harder than b
    # A follower at 15 m/s, 100 m behind a stopped car, stops without touching it.
    v, gap, dt = 15.0, 100.0, 0.1
    min_gap = gap
    for _ in range(1000):
        v = max(0.0, v + float(accel(v, gap, v)) * dt)
        gap -= v * dt
        min_gap = min(min_gap, gap)
    assert v == pytest.approx(0.0, abs=1e-3)
    assert min_gap > 0.5 * IDM["min_gap_m"]


def test_equilibrium_gap_gives_zero_acceleration():
    v = np.array([5.0, 10.0, 12.0])
    s_eq = (IDM["min_gap_m"] + v * IDM["tau_s"]) / np.sqrt(1 - (v / IDM["desired_speed_mps"]) ** 4)
    np.testing.assert_allclose(accel(v, s_eq, 0.0), 0.0, atol=1e-9)
    assert (accel(v, 0.8 * s_eq, 0.0) < 0).all()
    assert (accel(v, 1.2 * s_eq, 0.0) > 0).all()


def test_idm_broadcasts_per_vehicle_parameters():
    v = np.array([10.0, 10.0])
    a = idm_accel(
        v,
        np.array([1e6, 1e6]),
        np.zeros(2),
        np.array([10.0, 20.0]),
        np.full(2, 1.2),
        np.array([1.0, 2.0]),
        np.full(2, 1.5),
        np.full(2, 2.0),
    )
    np.testing.assert_allclose(a, [0.0, 2.0 * (1 - 0.5**4)], atol=1e-8)


# --------------------------------------------------------------------------- loss terms


def losses(gaps, mask=None, mean_target=125.0, d_min=115.0, d_max=140.0):
    gaps = np.atleast_2d(np.asarray(gaps, float))
    mask = np.ones_like(gaps, bool) if mask is None else np.atleast_2d(np.asarray(mask, bool))
    b = gaps.shape[0]
    return spacing_losses(gaps, mask, np.full(b, mean_target), np.full(b, d_min), np.full(b, d_max))


def test_spacing_losses_zero_on_target():
    out = losses([125.0] * 5)
    for name in ("L_mean", "L_min", "L_max", "L_var"):
        assert out[name][0] == pytest.approx(0.0, abs=1e-15), name


def test_spacing_losses_penalise_only_violations():
    inside = losses([116.0, 139.0, 120.0, 130.0])
    assert inside["L_min"][0] == 0.0 and inside["L_max"][0] == 0.0
    assert inside["L_mean"][0] > 0 and inside["L_var"][0] > 0  # off-mean, spread

    low = losses([100.0, 125.0, 125.0, 150.0])
    assert low["L_min"][0] == pytest.approx(((115 - 100) / 115) ** 2 / 4)
    assert low["L_max"][0] == pytest.approx(((150 - 140) / 140) ** 2 / 4)

    only_low = losses([100.0, 125.0, 125.0, 125.0])
    assert only_low["L_min"][0] > 0 and only_low["L_max"][0] == 0.0


def test_spacing_losses_ignore_masked_gaps():
    base = losses([120.0, 130.0, 125.0, 125.0], mask=[1, 1, 1, 1])
    masked = losses([120.0, 130.0, 125.0, 125.0, 1.0, 900.0], mask=[1, 1, 1, 1, 0, 0])
    for name in base:
        assert masked[name][0] == pytest.approx(base[name][0], abs=1e-15), name
    empty = losses([1.0, 900.0], mask=[0, 0])
    for name in empty:
        assert empty[name][0] == 0.0, name


def test_spacing_losses_batched_rows_are_independent():
    two = losses([[125.0, 125.0], [100.0, 150.0]])
    assert two["L_min"].shape == (2,)
    assert two["L_min"][0] == 0.0 and two["L_min"][1] > 0


def test_speed_loss():
    assert speed_loss(np.array([[12.0, 12.0]]), np.array([12.0]))[0] == 0.0
    assert speed_loss(np.array([[11.0, 13.0]]), np.array([12.0]))[0] == 0.0  # the mean counts
    np.testing.assert_allclose(
        speed_loss(np.array([[10.0, 12.0], [12.0, 12.0]]), np.array([12.0, 10.0])),
        [(11 / 12 - 1) ** 2, (12 / 10 - 1) ** 2],
    )


def test_speed_loss_with_a_scale_charges_a_bias_of_the_scale_one():
    """policy.macro_speed_scale_mps: a 0.1 m/s bias costs 1, as a 100% error in the paper's."""
    v = np.array([[12.05, 12.15], [12.0, 12.0]])
    np.testing.assert_allclose(speed_loss(v, np.array([12.0, 12.0]), 0.1), [1.0, 0.0])
    # 4 cm/s at 12 m/s: 1e-5 in the paper's form, 0.16 with s = 0.1 m/s
    assert speed_loss(np.array([[12.04]]), np.array([12.0]))[0] < 2e-5
    assert speed_loss(np.array([[12.04]]), np.array([12.0]), 0.1)[0] == pytest.approx(0.16)


# --------------------------------------------------------------------------- safe speed


def test_brake_gap_is_the_euler_braking_distance():
    v, b, dt = np.array([0.0, 1.0, 5.0, 14.6, 12.0]), np.array([3.0, 3.0, 3.0, 15.0, 1.1]), 0.5
    want = []
    for v0, b0 in zip(v, b, strict=True):
        x, u = 0.0, v0
        while u > 0:
            u = max(u - b0 * dt, 0.0)
            x += u * dt
        want.append(x)
    np.testing.assert_allclose(brake_gap(v, b, dt), want, atol=1e-12)
    cont = v**2 / (2 * b)
    assert np.all(brake_gap(v, b, dt) <= cont + 1e-12)
    assert brake_gap(v, b, dt)[3] < cont[3] - 3.0  # hard braking in coarse steps: half of it


def test_safe_speed_meets_the_gipps_condition_with_equality():
    gap, v_l, b, b_l, dt = np.array([0.0, 3.0, 40.0]), np.array([0.0, 5.0, 12.0]), 3.0, 6.0, 0.5
    v = safe_speed(gap, v_l, b, b_l, dt)
    np.testing.assert_allclose(v * dt + brake_gap(v, b, dt), gap + brake_gap(v_l, b_l, dt))
    assert v[0] == 0.0  # no room, a standing leader: stand
    assert np.all(np.diff(v) > 0)  # more room, a faster leader: faster


def test_safe_speed_keeps_a_gap_of_one_step_behind_a_leader_of_the_same_speed_and_decel():
    """b_l = b: the follower may drive at its leader's speed with a gap of v dt (it covers
    what the leader does, one step later), as in the continuous form."""
    v_l, b, dt = np.array([2.0, 5.0, 8.0]), 3.0, 0.5
    np.testing.assert_allclose(safe_speed(v_l * dt, v_l, b, b, dt), v_l)
    assert np.all(safe_speed(v_l * dt - 0.1, v_l, b, b, dt) < v_l)  # closer: slower


def test_safe_speed_counts_a_negative_gap_as_none_and_takes_per_vehicle_decels():
    v = safe_speed(np.array([-1.0, 0.0]), np.array([6.0, 6.0]), np.array([3.0, 3.0]), 6.0, 0.5)
    assert v[0] == v[1] > 0.0  # the leader's own braking distance still leaves room
    per = safe_speed(np.array([5.0, 5.0]), np.array([5.0, 5.0]), np.array([1.0, 4.0]), 6.0, 0.5)
    assert per[1] > per[0]  # a vehicle that brakes harder may go faster


def test_following_at_the_safe_speed_never_collides_when_the_leader_brakes():
    """Euler steps as SUMO's (v' commanded, x' = x + v' dt): a follower that takes the safe
    speed, then brakes at b, stops behind a leader that brakes at b_l from the same moment,
    for random gaps and speeds, whichever of the two brakes harder (with the leader's
    distance at b_l alone, a follower with b > b_l ran up to 37 m into its leader here)."""
    rng = np.random.default_rng(0)
    n, dt = 2000, 0.5
    gap = rng.uniform(0.0, 30.0, n)
    v_l = rng.uniform(0.0, 15.0, n)
    b = rng.uniform(1.0, 6.0, n)
    b_l = b * rng.uniform(0.3, 3.0, n)
    assert (b_l < b).sum() > 200
    v = safe_speed(gap, v_l, b, b_l, dt)
    for _ in range(200):
        v_l = np.maximum(v_l - b_l * dt, 0.0)
        gap = gap + (v_l - v) * dt
        assert gap.min() > -1e-9
        v = np.maximum(v - b * dt, 0.0)
    assert np.all(v == 0.0) and np.all(v_l == 0.0)


def test_a_follower_capped_at_the_safe_speed_never_collides_nor_brakes_beyond_its_decel():
    """Closed loop: a follower that always asks for full acceleration, capped at the safe
    speed every step, behind a leader taking random accelerations within [-b_l, 2] m/s^2,
    for any ratio of the two decels: the gap never goes below zero, and the cap never asks
    the follower to brake harder than its own b (Krauss' invariant: it is never caught
    out), so a layer of such caps does not pass hard braking on to the next follower."""
    rng = np.random.default_rng(1)
    n, dt = 2000, 0.5
    gap = rng.uniform(0.0, 30.0, n)
    v_l = rng.uniform(0.0, 15.0, n)
    b = rng.uniform(1.0, 6.0, n)
    b_l = b * rng.uniform(0.3, 3.0, n)
    v = np.minimum(v_l, safe_speed(gap, v_l, b, b_l, dt))
    for _ in range(400):
        v_l_next = np.maximum(v_l + rng.uniform(-b_l, 2.0) * dt, 0.0)
        cmd = np.minimum(v + 3.0 * dt, safe_speed(gap, v_l, b, b_l, dt))
        assert np.all((v - cmd) / dt <= b + 1e-9)
        gap = gap + (v_l_next - cmd) * dt
        assert gap.min() > -1e-9
        v, v_l = cmd, v_l_next
    assert v.max() > 10.0  # not all standing: the loop exercised moving traffic


def test_safe_speed_with_constant_arrays_is_the_python_float_formula_to_the_bit():
    """``safe_speed`` and ``brake_gap`` with their constants as 0-d arrays (stop 44, speed
    only) give the Python-float formula's values to the bit on float64 rows, over more step
    lengths than the constants cache keeps (it stays at 16)."""
    from macromicro_sumo.road import physics

    def brake_gap_ref(v, b, dt):
        reduction = np.multiply(b, dt)
        steps = np.floor(np.asarray(v) / reduction)
        return dt * (steps * v - reduction * steps * (steps + 1.0) / 2.0)

    def safe_speed_ref(gap, v_l, b, b_l, dt):
        room = np.maximum(gap, 0.0) + brake_gap_ref(v_l, np.maximum(b, b_l), dt)
        bdt2 = np.multiply(b, dt**2)
        n = np.floor((-1.0 + np.sqrt(1.0 + 8.0 * room / bdt2)) / 2.0)
        return (room + bdt2 * n * (n + 1.0) / 2.0) / (dt * (n + 1.0))

    rng = np.random.default_rng(44)
    for k in range(24):
        dt = 0.05 + 0.05 * k
        gap, v_l = rng.uniform(-1.0, 200.0, 64), rng.uniform(0.0, 40.0, 64)
        b, b_l = rng.uniform(1.0, 9.0, 64), rng.uniform(1.0, 9.0, 64)
        got, want = physics.safe_speed(gap, v_l, b, b_l, dt), safe_speed_ref(gap, v_l, b, b_l, dt)
        assert got.dtype == np.float64 and np.array_equal(got.view(np.int64), want.view(np.int64))
        assert np.array_equal(physics.brake_gap(v_l, b, dt), brake_gap_ref(v_l, b, dt))
    assert len(physics._STEP_CONSTANTS) <= 16


def test_constants_are_read_only_0d_float64_arrays_made_once():
    """``constants`` (the deployment's per-step operands): the values as read-only 0-d
    float64 arrays, the same objects on the next call (made once), none writable."""
    from macromicro_sumo.road.physics import constants

    lo, hi = constants(-4.5, 2.6)
    assert lo.shape == () and lo.dtype == np.float64 and float(lo) == -4.5 and float(hi) == 2.6
    assert constants(-4.5, 2.6)[0] is lo
    with pytest.raises(ValueError):
        lo[...] = 0.0
