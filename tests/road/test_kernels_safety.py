"""road/kernels.c: ``road.vtype.command_speeds`` and ``deploy.safety.safety_cap`` compiled
give numpy's values and counts to the bit on random inputs of the deployment's forms (and
the forms it declines are left to numpy)."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.deploy import safety
from macromicro_sumo.road import vtype

kernels = pytest.importorskip(
    "macromicro_sumo.road.kernels", reason="road/kernels.c not built (no C compiler)"
)


SWITCHES = ("_command_speeds", "_safety_cap", "_leader_safe_speed")


def numpy_only(module, f, *args):
    """``module.f`` with the kernels switched off: numpy's form."""
    names = [n for n in SWITCHES if hasattr(module, n)]
    saved = [getattr(module, n) for n in names]
    assert all(k is not None for k in saved)  # built: the kernels answer otherwise
    for n in names:
        setattr(module, n, None)
    try:
        return f(*args)
    finally:
        for n, k in zip(names, saved, strict=True):
            setattr(module, n, k)


def same(got, want) -> None:
    if isinstance(want, tuple):
        assert got[1:] == want[1:]
        got, want = got[0], want[0]
    assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


@pytest.mark.parametrize("dt", [0.1, 0.5, 1.0])
def test_command_speeds_to_the_bit(dt: float) -> None:
    rng = np.random.default_rng(50)
    assert vtype._kernels is kernels
    for n in (1, 2, 7, 42, 301):
        for _ in range(30):
            obs = rng.uniform(0.0, 40.0, (n, 6))
            obs[rng.random(n) < 0.2, 0] = 0.0
            accel = rng.uniform(-9.0, 5.0, n)
            a_min = np.maximum(np.array(-4.5), -rng.choice([3.0, 4.5, 7.5], n))
            for args in (
                (obs[:, 0], accel, dt, a_min, 2.6, rng.choice([np.inf, 30.0, 8.0], n)),
                (obs[:, 0], accel, dt, -4.5, np.minimum(rng.uniform(0.5, 3, n), 2.6), np.inf),
                (obs[:, 0].copy(), accel, dt, np.array(-3.0), np.array(2.0), 33.3),
            ):
                same(vtype.command_speeds(*args), numpy_only(vtype, vtype.command_speeds, *args))
    # The deployment's form is the kernel's: it answers, not numpy.
    out = np.full(3, np.nan)
    assert kernels.command_speeds(obs[:3, 0], accel[:3], dt, -4.5, 2.6, np.inf, out) is True
    assert np.isfinite(out).all()


def test_command_speeds_other_forms_left_to_numpy() -> None:
    v, a = np.ones(4), np.linspace(-5, 5, 4)
    for args in ((v, a.astype(np.float32), 0.1, -4.5, 2.6, np.inf), (v, a, 1, -4.5, 2.6, 9.0)):
        out = np.full(4, 7.0)
        assert kernels.command_speeds(*args, out) is False and (out == 7.0).all()
        same(vtype.command_speeds(*args), numpy_only(vtype, vtype.command_speeds, *args))


def layer_draws(rng: np.random.Generator, n: int):
    """A step's operands of ``safety_cap`` as the drivers pass them: obs (speed, limit,
    gap, delta v, ...), SUMO's gaps, decels, driven leaders' indices (-1: none)."""
    obs = np.column_stack(
        [
            rng.uniform(0.0, 35.0, n),
            rng.choice([13.89, 27.78, 44.4], n),
            rng.uniform(0.0, 200.0, n),
            rng.uniform(-8.0, 8.0, n),
            rng.uniform(0.0, 40.0, n),
            rng.uniform(0.0, 400.0, n),
        ]
    )
    obs[rng.random(n) < 0.25, 0] = 0.0  # standing
    obs[:, 3] = np.where(rng.random(n) < 0.5, obs[:, 0], obs[:, 3])  # standing leaders
    gap = rng.uniform(-1.0, 150.0, n)
    gap[rng.random(n) < 0.2] = 1000.0  # no leader
    decel = rng.choice([4.5, 4.0, 7.5, 1.43, 2.6], n)
    lead_decel = rng.choice([4.5, 9.0, 2.0, 1.22], n)
    lead = np.where(rng.random(n) < 0.6, rng.integers(0, n, n), -1)
    cmd = np.maximum(obs[:, 0] + rng.uniform(-6.0, 3.0, n) * 0.1, 0.0)
    cmd[rng.random(n) < 0.1] = 0.0
    return cmd, obs, gap, decel, lead_decel, lead


@pytest.mark.parametrize("dt", [0.1, 0.5, 1.0])
def test_safety_cap_to_the_bit(dt: float) -> None:
    """Every form a deployment passes (floor share one or per vehicle, floor_safe, the
    start rules on all or some, vmax and a_max per vehicle or one), with and without a
    driven leader commanded below what safe_speed assumed (the kernel declines those)."""
    rng = np.random.default_rng(int(dt * 10))
    assert safety._kernels is kernels
    answered = declined = 0
    for n in (1, 2, 7, 42, 301):
        for trial in range(60):
            cmd, obs, gap, decel, lead_decel, lead = layer_draws(rng, n)
            lead_speed = obs[:, 0] - obs[:, 3]
            safe = safety.leader_safe_speed(obs, gap, decel, lead_decel, dt, lead_speed)
            a_max = rng.choice([2.6, 1.0]) if trial % 2 else rng.uniform(0.5, 2.6, n)
            share = 0.2 if trial % 3 else np.where(obs[:, 0] < 1.0, 0.2, 0.0)
            vmax = np.inf if trial % 4 else rng.choice([np.inf, 20.0], n)
            floor_safe = None
            if trial % 5 == 1:
                floor_safe = safety.reaction_safe_speed(gap, lead_speed, decel, lead_decel, dt, 1.0)
            start = None
            if trial % 3 == 2:
                on = None if trial % 2 else rng.random(n) < 0.5
                start = (a_max, 0.5, on)
            if trial % 7 == 3:  # chains of driven leaders braking beyond safe_speed's
                cmd = np.zeros(n)
            args = (cmd, obs, gap, decel, lead_decel, lead, dt, a_max, share, safe)
            args += (lead_speed, vmax, floor_safe, start)
            want = numpy_only(safety, safety.safety_cap, *args)
            same(safety.safety_cap(*args), want)
            s = (None, 1.0, None) if start is None else (a_max, 1.0 - 0.25 * dt, start[2])
            out = np.empty(n)
            got = kernels.safety_cap(
                cmd, obs[:, 0], obs[:, 1], safe, floor_safe, a_max, dt, share, vmax, *s,
                decel, lead_decel, lead, lead_speed, safety._BEHIND_MARGIN,
                safety._TOLERANCE, out,
            )  # fmt: skip
            if got is not None:
                answered += 1
                assert got == want[1:] and out.tobytes() == want[0].tobytes()
            else:
                declined += 1
    # Both paths met (random leaders chain more often than a road's: 1 step in 22 on
    # Bremen's policy run declines).
    assert answered > 80 and declined > 20


def test_safety_cap_other_forms_left_to_numpy() -> None:
    """A float32 observation, a leader index beyond the vehicles: None, numpy answers (and
    raises as it does)."""
    cmd, obs, gap, decel, lead_decel, lead = layer_draws(np.random.default_rng(9), 12)
    lead_speed = obs[:, 0] - obs[:, 3]
    safe = safety.leader_safe_speed(obs, gap, decel, lead_decel, 0.1, lead_speed)
    base = (decel, lead_decel, lead, lead_speed, safety._BEHIND_MARGIN, safety._TOLERANCE)
    o32 = obs.astype(np.float32)
    for v, lim, ld in ((o32[:, 0], o32[:, 1], lead), (obs[:, 0], obs[:, 1], lead + 12)):
        ops = (cmd, v, lim, safe, None, 2.6, 0.1, 0.2, np.inf, None, 1.0, None)
        assert kernels.safety_cap(*ops, *base[:2], ld, *base[3:], np.empty(12)) is None
    args = (cmd, obs, gap, decel, lead_decel, lead, 0.1, 2.6, 0.2, safe, lead_speed)
    same(safety.safety_cap(*args), numpy_only(safety, safety.safety_cap, *args))
    bad = (cmd, obs, gap, decel, lead_decel, np.full(12, 40), 0.1, 2.6, 0.2, safe, lead_speed)
    with pytest.raises(IndexError):
        safety.safety_cap(*bad)


@pytest.mark.parametrize("dt", [0.1, 0.5, 1.0])
def test_leader_safe_speed_to_the_bit(dt: float) -> None:
    """The safe speed behind each observed leader, no leader (gap at or past
    NO_LEADER_GAP_M, NaN too) inf, red lines or not: numpy's values."""
    rng = np.random.default_rng(int(dt * 100))
    for n in (1, 3, 42, 301):
        for trial in range(30):
            _, obs, gap, decel, lead_decel, _ = layer_draws(rng, n)
            gap[rng.random(n) < 0.05] = np.nan
            red = None
            if trial % 2:
                red = np.where(rng.random(n) < 0.3, rng.uniform(0.0, 200.0, n), np.inf)
            args = (obs, gap, decel, lead_decel, dt, None, red)
            with np.errstate(invalid="ignore"):
                want = numpy_only(safety, safety.leader_safe_speed, *args)
                got = safety.leader_safe_speed(*args)
            same(got, want)
    out = np.empty(n)
    dts = safety.step_constants(dt)
    v_l = obs[:, 0] - obs[:, 3]
    assert kernels.leader_safe_speed(gap, v_l, decel, lead_decel, *dts, out, 1000.0) is True
    assert kernels.leader_safe_speed(gap, v_l, decel, lead_decel, *dts, out, gap) is False
