"""The Krauss prior's relaxation time where the recorded pairs leave it at its bound
(``policy.relax_choice``): chosen against the training runs' induction loops (SUMO's own,
``DemandCore.loop_table``; tests/env/test_demand_loops.py checks them against the truth's)
by driving their demand, warm-up included, with the prior alone. Real SUMO: one run of
ring_two_lane (its fleet departs standing; a few seconds of SUMO)."""

from __future__ import annotations

import pytest

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.prior import RELAX_UPPER_S
from macromicro_sumo.policy.relax_choice import (
    LoopFit,
    choose_relax,
    pick_relax,
    relax_unidentified,
)

# ring_two_lane's fitted prior (stop 31's manifest, rounded) with relax_s at its bound, as
# the fit leaves it: no recorded pair shows free acceleration.
PRIOR = {
    "speed_factor": 0.88,
    "accel_mps2": 2.6,
    "decel_mps2": 2.3,
    "tau_s": 1.65,
    "min_gap_m": 0.0,
    "veh_length_m": 5.0,
    "dt_s": 0.5,
    "relax_s": RELAX_UPPER_S,
}


@pytest.fixture(scope="module")
def ring(ring_two_lane_short):
    """ring_two_lane, one run: a 60 s warm-up, 60 s recorded; its loops every 60 s."""
    return ring_two_lane_short


def test_a_relaxation_at_its_bound_is_chosen_on_the_standing_start(ring):
    """With relax_s at its bound the fleet closes on its desired speed within 10 s and
    passes fewer vehicles over the loops in its first minute than the truth's; the choice
    keeps a shorter one, whose counts are closer, and records every candidate."""
    sc, truth = ring
    assert relax_unidentified(PRIOR)
    assert not relax_unidentified({**PRIOR, "relax_s": 0.8 * RELAX_UPPER_S})
    chosen, record = choose_relax(
        sc,
        PRIOR,
        lambda: DemandCore(sc, truth, truth.runs, 10),
        candidates=(1.0, 3.0, RELAX_UPPER_S),
        span_s=0.0,  # the warm-up's minute alone
    )
    fits = record["candidates"]
    assert set(fits) == {"1", "3", "10"} and record["runs"] == [0]
    assert chosen < RELAX_UPPER_S
    assert fits[f"{chosen:g}"]["count_rmse"] < fits["10"]["count_rmse"]
    assert fits["10"]["passages"] < fits["1"]["passages"]  # the slower start passes fewer
    assert all(f["collisions"] == 0 and f["teleports"] == 0 for f in fits.values())


def _fit(count_rmse: float, collisions: int) -> LoopFit:
    return LoopFit(count_rmse, 0.0, 100, collisions, 0)


def test_the_choice_keeps_the_fitted_relaxation_where_every_run_crashed():
    """Counts of runs that collided are no measurement (drawn net 311: every candidate
    collided 606-906 times and the counts picked 7 s, which trained a worse policy): the
    fitted T stays; a collision-free candidate is chosen over a closer one that crashed,
    and equals keep the first (the larger T)."""
    crashed = [(10.0, _fit(85.7, 754)), (7.0, _fit(71.1, 606)), (5.0, _fit(84.3, 906))]
    assert pick_relax(crashed, 10.0) == 10.0
    mixed = [(10.0, _fit(8.1, 0)), (7.0, _fit(2.0, 3)), (5.0, _fit(3.9, 0)), (3.0, _fit(3.9, 0))]
    assert pick_relax(mixed, 10.0) == 5.0
    assert pick_relax([(10.0, _fit(float("nan"), 0)), (5.0, _fit(6.0, 0))], 10.0) == 5.0
