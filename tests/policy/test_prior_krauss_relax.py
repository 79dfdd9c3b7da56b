"""The Krauss prior's relaxation time where the recorded pairs leave it at its bound
(``policy.relax_choice``): each candidate's prior alone deployed on the training runs by
the project's one prior-alone scorer (``policy.prior_choice.PriorDeploy``,
``deploy.prior_score.deploy_prior``: the deployment's safety layer and drivers, from
SUMO's first step), the lowest speed RMSE against the truth's detectors kept. Real SUMO:
ring_two_lane cut to three runs of a 60 s warm-up and 60 s recorded (its fleet departs
standing; a few seconds of SUMO per deployment)."""

from __future__ import annotations

import pytest

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.deploy.prior_score import deploy_prior
from macromicro_sumo.policy.prior import RELAX_UPPER_S
from macromicro_sumo.policy.prior_choice import PriorDeploy
from macromicro_sumo.policy.relax_choice import choose_relax, relax_unidentified

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
    """ring_two_lane, three runs (one trains, one validates, one is held out): a 60 s
    warm-up, 60 s recorded; its loops every 60 s."""
    return ring_two_lane_short


def test_the_relaxation_is_the_candidate_whose_prior_alone_deploys_closest(ring):
    """With relax_s at its bound the fleet, departing standing, closes on its desired speed
    within 10 s and its first minute runs slow; each candidate's prior alone is deployed
    on the training run, the one with the lowest speed RMSE against the truth's detectors
    is kept (a shorter one than the bound), every candidate's figures are recorded, and the
    kept one's figure is what deploying it again gives."""
    sc, truth = ring
    assert relax_unidentified(PRIOR)
    assert not relax_unidentified({**PRIOR, "relax_s": 0.8 * RELAX_UPPER_S})
    deploy = PriorDeploy(deploy_prior, truth.folder)
    calls = []

    def score(params):
        calls.append(params["relax_s"])
        return deploy(sc, params)

    chosen, record = choose_relax(PRIOR, score, 0.5, candidates=(0.2, 3.0, RELAX_UPPER_S))
    assert calls == [RELAX_UPPER_S, 3.0, 0.5]  # the step at least; each deployed once
    cand = record["candidates"]
    assert set(cand) == {"10", "3", "0.5"} and record["chosen_s"] == chosen
    rmse = {k: c["speed_rmse_mps"] for k, c in cand.items()}
    assert rmse[f"{chosen:g}"] == min(rmse.values())
    assert chosen < RELAX_UPPER_S and rmse["10"] > rmse[f"{chosen:g}"] + 0.05
    assert all(c["collisions"] == 0 and c["teleports"] == 0 for c in cand.values())
    assert all(c["runs"] == cand["10"]["runs"] for c in cand.values())
    train = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["train"]
    assert cand["10"]["runs"] == [int(r) for r in train]  # never validation nor held out
    again = deploy(sc, {**PRIOR, "relax_s": chosen})
    assert again["speed_rmse_mps"] == pytest.approx(rmse[f"{chosen:g}"], abs=1e-9)


def test_the_ranking_puts_a_collision_free_deployment_first_and_keeps_the_larger_of_equals():
    """A deployment that collided ranks behind any that did not (the deployment's safety
    layer should never let one collide: a defect, not a figure), a NaN RMSE last, and equal
    figures keep the larger T (the fit's side)."""
    figures = {
        10.0: {"speed_rmse_mps": 0.41, "collisions": 0},
        7.0: {"speed_rmse_mps": 0.30, "collisions": 0},
        5.0: {"speed_rmse_mps": 0.30, "collisions": 0},
        3.0: {"speed_rmse_mps": 0.10, "collisions": 2},
        1.0: {"speed_rmse_mps": float("nan"), "collisions": 0},
    }
    chosen, record = choose_relax(PRIOR, lambda p: figures[p["relax_s"]], 0.5, tuple(figures))
    assert chosen == 7.0 and list(record["candidates"]) == ["10", "7", "5", "3", "1"]
    assert record["fitted_s"] == RELAX_UPPER_S
    crashed = {t: {**f, "collisions": 1} for t, f in figures.items()}
    chosen, _ = choose_relax(PRIOR, lambda p: crashed[p["relax_s"]], 0.5, tuple(crashed))
    assert chosen == 3.0  # all collided: still the lowest RMSE, none preferred on that ground
