"""The Krauss prior's relaxation time where the recorded pairs leave it at its bound
(``policy.relax_choice``): chosen against the training runs' induction loops by driving
their demand, warm-up included, with the prior alone. Real SUMO: one run of ring_two_lane
(its fleet departs standing; a few seconds of SUMO)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.prior import RELAX_UPPER_S
from macromicro_sumo.policy.relax_choice import Loops, choose_relax, relax_unidentified
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[2]
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
def ring(tmp_path_factory: pytest.TempPathFactory):
    """ring_two_lane, one run: a 60 s warm-up, 60 s recorded; its loops every 60 s."""
    sc = load_scenario(ROOT / "scenarios" / "ring_two_lane.toml")
    sc = replace(sc, simulation=replace(sc.simulation, n_runs=1, warmup_s=60.0, duration_s=60.0))
    folder = tmp_path_factory.mktemp("r2l_relax")
    simulate_section(sc, folder / "gt", progress=False)
    return sc, load_section_truth(folder / "gt", sc)


def test_the_loops_read_off_a_replay_count_as_sumos_own(ring):
    """The truth's run replayed by the demand core with nobody driven (SUMO's models, the
    truth's seed): the vehicles ``Loops`` counts per interval, all loops together, are
    SUMO's loops' counts within one, and after the standing start their mean speed is
    SUMO's within 0.05 m/s."""
    sc, truth = ring
    det = truth.detectors[truth.detectors["run"] == 0]
    loops = det.drop_duplicates("detector_id").reset_index(drop=True)
    edges = np.unique(np.concatenate([det["begin_s"], det["end_s"]]))
    count = np.zeros((len(loops), len(edges) - 1))
    speed = np.zeros_like(count)
    core = DemandCore(sc, truth, np.array([0]), 10)
    try:
        core.reset(0, core.dt)
        reader = Loops(loops)
        for _ in range(int(round(edges[-1] / core.dt)) - 1):
            core.step(np.zeros(0))
            loop, v = reader.passages(core)
            k = np.searchsorted(edges, core.time_s(), side="left") - 1
            np.add.at(count[:, k], loop, 1.0)
            np.add.at(speed[:, k], loop, v)
    finally:
        core.close()
    true_count = det.pivot(index="detector_id", columns="begin_s", values="n_veh")
    true_count = true_count.loc[loops["detector_id"]].to_numpy()
    assert count.sum() > 100  # the premise: the fleet passes the loops
    np.testing.assert_allclose(count.sum(axis=0), true_count.sum(axis=0), atol=1.0)
    later = det[det["begin_s"] > 0]
    true_mean = np.average(later["speed_mps"], weights=later["n_veh"])
    assert speed[:, 1:].sum() / count[:, 1:].sum() == pytest.approx(true_mean, abs=0.05)


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
