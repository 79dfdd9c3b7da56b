"""``env.driver_tau.DriverTaus``' hand-over: a driver asked with its observations and the
step starts at the tau its first observed state supports (where its draw is longer) and
rises to its draw at ``HANDOVER_RATE_S_PER_S``, so that the Krauss prior does not brake
at the first driven step only because the drawn tau is longer than the gap the vehicle
arrived with (drawn 502: 151 of 159 emergency brakings there). Asked without them, the
draws are as before. Observations of real SUMO (tests/conftest.py's
``ring_driver_follow``: the recorded pairs of the ring), the prior in torch."""

from __future__ import annotations

import numpy as np
import torch

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS
from macromicro_sumo.env.driver_tau import (
    HANDOVER_RATE_S_PER_S,
    DriverTaus,
    supported_taus,
)
from macromicro_sumo.evaluation.micro_data import keyed_micro_pairs
from macromicro_sumo.policy.prior import krauss_prior_accel

# A long-tau population: every draw at 1.6-2.2 s, longer than most ring gaps support.
LONG_Q = np.interp(QUANTILE_LEVELS, [0.0, 1.0], [1.6, 2.2])


def prior_accel(obs: np.ndarray, prior: dict, taus: np.ndarray) -> np.ndarray:
    p = {k: torch.tensor(float(v), dtype=torch.float64) for k, v in prior.items()}
    p = {**p, "tau_s": torch.as_tensor(taus, dtype=torch.float64)}
    return krauss_prior_accel(torch.as_tensor(obs, dtype=torch.float64), p).numpy()


def test_handover_starts_at_the_supported_tau_and_rises_to_the_draw(ring_driver_follow) -> None:
    sc, _, truth, prior, _, _ = ring_driver_follow
    obs, _, keys = keyed_micro_pairs(sc, truth, truth.runs[:1])
    # Each driver's first recorded pair: the state it is handed over in.
    first: dict[str, int] = {}
    for i, (_, vid) in enumerate(keys):
        first.setdefault(vid, i)
    vids = list(first)
    o = obs[list(first.values())]
    run = keys[0][0]
    drawn = DriverTaus(LONG_Q, sc, run)(vids)  # no prior: the draws, as before
    assert np.array_equal(DriverTaus(LONG_Q, sc, run, prior)(vids), drawn)  # no obs: same
    ok = supported_taus(o, prior)
    # The supported tau is where the prior's safe speed is the speed: no braking there.
    moving = np.isfinite(ok) & (ok > 0.05)
    assert moving.sum() >= 5, moving.sum()
    a_ok = prior_accel(o[moving], prior, ok[moving])
    free = prior_accel(o[moving], prior, np.full(moving.sum(), 1e-6))
    np.testing.assert_allclose(np.minimum(a_ok, 0.0), np.minimum(free, 0.0), atol=1e-6)
    longer = drawn > np.maximum(ok, LONG_Q[0]) + 0.1
    assert longer.sum() >= 3, longer.sum()
    # Handed over at step 7: the longer draws start at the supported tau (at least the
    # lowest quantile), the others at their draw.
    taus = DriverTaus(LONG_Q, sc, run, prior)
    got = taus(vids, o, 7)
    want = np.minimum(drawn, np.maximum(ok, LONG_Q[0]))
    np.testing.assert_allclose(got, want)
    assert np.all(got[longer] < drawn[longer] - 0.1)
    # With the draw the prior brakes at the first step; with the hand-over's tau it does not
    # brake harder than with the supported one.
    a_drawn = prior_accel(o[longer], prior, drawn[longer])
    a_got = prior_accel(o[longer], prior, got[longer])
    assert np.all(a_got > a_drawn + 0.1)
    # Later steps: up at the rate, whatever the state then, to the draw and no further.
    dt = sc.simulation.step_length_s
    later = taus(vids, o[::-1].copy(), 7 + 4)
    np.testing.assert_allclose(later, np.minimum(drawn, want + HANDOVER_RATE_S_PER_S * dt * 4))
    np.testing.assert_allclose(taus(vids, o, 7 + 1000), drawn)
