"""road/kernels.c: ``road.physics.safe_speed`` compiled gives numpy's values to the bit, and
hands back to numpy any operand it does not take."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.deploy import policy_batch
from macromicro_sumo.evaluation.krauss_fit import KraussParams, krauss_policy_accel
from macromicro_sumo.road import physics

kernels = pytest.importorskip(
    "macromicro_sumo.road.kernels", reason="road/kernels.c not built (no C compiler)"
)


def numpy_safe_speed(*args) -> np.ndarray:
    """``physics.safe_speed`` with the kernel switched off: numpy's form."""
    saved, physics._kernels = physics._kernels, None
    try:
        return physics.safe_speed(*args)
    finally:
        physics._kernels = saved


def draws(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    gap = rng.uniform(-5.0, 300.0, n)
    gap[rng.random(n) < 0.2] = 1000.0  # no leader
    gap[rng.random(n) < 0.05] = -0.0
    v_l = rng.uniform(0.0, 40.0, n)
    v_l[rng.random(n) < 0.15] = 0.0  # standing leaders
    b = rng.choice([4.5, 4.0, 7.5, 1.43, 2.6], n)
    b_l = rng.choice([4.5, 9.0, 2.0, 1.22], n)
    return gap, v_l, b, b_l


@pytest.mark.parametrize("dt", [0.1, 0.5, 1.0, 0.25])
def test_the_same_values_to_the_bit(dt: float) -> None:
    rng = np.random.default_rng(17)
    assert physics._kernels is kernels  # the physics module uses it
    for n in (1, 2, 7, 42, 301):
        for _ in range(40):
            gap, v_l, b, b_l = draws(rng, n)
            want = numpy_safe_speed(gap, v_l, b, b_l, dt)
            got = physics.safe_speed(gap, v_l, b, b_l, dt)
            assert got.tobytes() == want.tobytes()
            # Scalars and 0-d decels, a strided view of a table's column: broadcast as numpy.
            table = np.column_stack([v_l, gap])
            for args in (
                (gap, table[:, 0], 4.5, b_l),
                (gap, v_l, np.array(2.6), 9.0),
                (gap, v_l, b, b[:1]),
            ):
                want = numpy_safe_speed(*args, dt)
                got = physics.safe_speed(*args, dt)
                assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_the_kernels_take_a_deployments_operands() -> None:
    """What the deployment passes (vectors, strided columns, 0-d and Python floats) is the
    kernels' to answer, not numpy's: they say True (the tests above would pass on the
    fallback alone)."""
    gap, v_l, b, b_l = draws(np.random.default_rng(2), 9)
    dt, dt2 = physics.step_constants(0.1)
    table = np.column_stack([v_l, gap])
    for args in ((gap, v_l, b, b_l), (gap, table[:, 0], 4.5, b_l), (gap, v_l, np.array(2.6), 9.0)):
        out = np.full(9, np.nan)
        assert kernels.safe_speed(*args, dt, dt2, out) is True
        assert np.isfinite(out).all()
    obs = np.column_stack([v_l, np.full(9, 13.89), gap, v_l - 1.0, gap, gap])
    prior = policy_batch.krauss_batch(KraussParams(1.8, 2.6, 4.5, 1.0, 2.5, 1.0), 5.0, 0.1)
    consts = [c.cell_contents for c in prior.__closure__ if c.cell_contents.__class__ is tuple]
    out = np.full(9, np.nan)
    assert kernels.krauss_prior(obs, *consts[0], out) is True
    assert np.isfinite(out).all()


def test_nan_and_inf_as_numpy() -> None:
    gap = np.array([np.nan, np.inf, 5.0, 5.0, -np.inf, 0.0])
    v_l = np.array([3.0, 3.0, np.nan, np.inf, 3.0, 0.0])
    b = np.array([4.5, 4.5, 4.5, 4.5, 4.5, 4.5])
    b_l = np.array([9.0, 9.0, 9.0, np.nan, 9.0, 9.0])
    with np.errstate(all="ignore"):
        want = numpy_safe_speed(gap, v_l, b, b_l, 0.1)
    got = physics.safe_speed(gap, v_l, b, b_l, 0.1)
    assert got.tobytes() == want.tobytes()


def test_other_operands_left_to_numpy() -> None:
    """float32, a length that does not match, 2-D, a list: the kernel says False and does
    not write; safe_speed then answers as numpy does (its shapes, dtypes and errors)."""
    gap, v_l, b, b_l = draws(np.random.default_rng(3), 6)
    dt, dt2 = physics.step_constants(0.1)
    for args in (
        (gap.astype(np.float32), v_l, b, b_l),
        (gap, v_l[:5], b, b_l),
        (gap, v_l.reshape(2, 3), b, b_l),
        (gap, list(v_l), b, b_l),
    ):
        out = np.full(6, 7.0)
        assert kernels.safe_speed(*args, dt, dt2, out) is False
        assert (out == 7.0).all()
    got = physics.safe_speed(gap.astype(np.float32), v_l, b, b_l, 0.1)
    assert got.tobytes() == numpy_safe_speed(gap.astype(np.float32), v_l, b, b_l, 0.1).tobytes()
    with pytest.raises(ValueError):
        physics.safe_speed(gap, v_l[:5], b, b_l, 0.1)


def test_krauss_prior_the_same_values_to_the_bit() -> None:
    """deploy.policy_batch.krauss_batch's prior, compiled, against its numpy form (and so
    against evaluation.krauss_fit.krauss_policy_accel, tests/deploy/test_numpy_actor.py)."""
    assert policy_batch.kernels is kernels
    rng = np.random.default_rng(5)
    for trial in range(60):
        p = KraussParams(
            accel_mps2=rng.uniform(0.8, 3.0),
            decel_mps2=rng.uniform(2.0, 6.0),
            tau_s=rng.uniform(0.5, 2.0),
            min_gap_m=rng.uniform(1.0, 3.0),
            speed_factor=rng.uniform(0.8, 1.2),
            relax_s=rng.uniform(0.0, 3.0),
        )
        prior = policy_batch.krauss_batch(p, 5.0, 0.5 if trial % 2 else 0.1)
        n = int(rng.integers(1, 120))
        obs = np.column_stack(
            [
                rng.uniform(0.0, 40.0, n),
                rng.choice([13.89, 27.78, 33.33], n),
                rng.uniform(-2.0, 1000.0, n),
                rng.uniform(-10.0, 10.0, n),
                rng.uniform(0.0, 500.0, n),
                rng.uniform(0.0, 500.0, n),
            ]
        )
        obs[rng.random(n) < 0.1, 0] = 0.0
        got = prior(obs)
        policy_batch.kernels = None
        try:
            want = prior(obs)
            strided = prior(obs[:, :4].copy(order="F"))  # numpy's form on a column layout
        finally:
            policy_batch.kernels = kernels
        assert got.tobytes() == want.tobytes()
        assert prior(obs[:, :4].copy(order="F")).tobytes() == strided.tobytes()
        ref = krauss_policy_accel(obs, p, 5.0, 0.5 if trial % 2 else 0.1)
        np.testing.assert_array_equal(got, ref)
    out = np.full(3, 7.0)
    assert kernels.krauss_prior(np.zeros((3, 3)), *([1.0] * 11), out) is False  # < 4 columns
    assert kernels.krauss_prior(np.zeros((3, 4), np.float32), *([1.0] * 11), out) is False
    assert (out == 7.0).all()
