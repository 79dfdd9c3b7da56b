"""Stage I places the generated vehicles with their own length (``complete_section``'s
``generated_length_m``, ``section_scene.generated_extra``).

psi's smallest spacing is the shortest recorded vehicle plus the minimum gap. A generated
vehicle is as long as the section's typical one: where that is longer (5 m Krauss cars
beside 4.5 m IDM cars on the drawn motorways) a generated leader placed at psi's spacing
left its follower less than the minimum gap (fresh 1169, stop 46: a collision in Stage II's
evaluation), and the pair check had to drop such vehicles afterwards. Placed with its
length, every pair a generated vehicle is part of keeps the minimum gap bumper to bumper;
where the generated vehicle is the shortest's length nothing changes, to the bit.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch
from conftest import game_ramp_truth

from macromicro_sumo.data.section import section_snapshots
from macromicro_sumo.env.section_bank import typical_length
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_sampler import complete_section, generated_length
from macromicro_sumo.generator.section_scene import PSI_INDEX, shortest_length
from macromicro_sumo.road.leaders import section_leaders

BRAKE, T_MAX, SEED = 4.5, 8, 3
LONGER_M = 2.5  # the generated vehicles this much longer than the shortest recorded one


@pytest.fixture(scope="module")
def ramp(tmp_path_factory):
    """game/ramp's queue (a real SUMO run, half the vehicles observed): its snapshots, an
    untrained generator (seeded), the scenario and the truth."""
    sc, truth = game_ramp_truth(tmp_path_factory.mktemp("ramp"), "none")
    snaps = section_snapshots(truth, sc, np.unique(truth.runs))
    torch.manual_seed(0)
    return sc, truth, snaps, SectionGeneratorNet(32)


def _complete(ramp, length_m):
    sc, truth, snaps, net = ramp
    dt = sc.simulation.step_length_s
    k = snaps.k_true
    return complete_section(net, truth.section, snaps, k, T_MAX, SEED, BRAKE, dt, length_m)


def _digest(comp) -> str:
    md5 = hashlib.md5()
    for x in (comp.lane, comp.arc_m, comp.speed_mps, comp.valid, comp.generated):
        md5.update(np.ascontiguousarray(x).tobytes())
    return md5.hexdigest()


def _bumper_gaps(ramp, comp, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pair with a generated vehicle in it (along the environment's leaders): its
    front-to-back gap [m] (spacing less the leader's length: recorded, or ``length_m`` for a
    generated one) and the minimum gap it must keep (psi's s_min less the shortest)."""
    _, truth, snaps, _ = ramp
    n = snaps.arc_m.shape[1]
    shortest = shortest_length(snaps)
    gaps, floors = [], []
    for s in range(len(snaps)):
        on = np.flatnonzero(comp.valid[s])
        gen = comp.generated[s, on]
        lead, spacing = section_leaders(truth.section, comp.lane[s, on], comp.arc_m[s, on])
        rec = np.where(on < n, snaps.length_m[s, np.minimum(on, n - 1)], 0.0)
        length = np.where(gen, length_m, rec)
        j = np.maximum(lead, 0)
        pair = (lead >= 0) & (gen | gen[j])
        gaps.append(spacing[pair] - length[j][pair])
        floor = snaps.psi[s, PSI_INDEX["spacing_min_m"]] - shortest
        floors.append(np.full(int(pair.sum()), floor))
    return np.concatenate(gaps), np.concatenate(floors)


def test_generated_vehicles_keep_the_minimum_gap_with_their_length(ramp) -> None:
    """Generated vehicles LONGER_M longer than the shortest: every generated pair keeps the
    minimum gap behind the leader's rear, and the pair check has nothing left to drop for
    it; placed at psi's s_min instead (no length: the placement before stop 47) the same
    scenes have pairs closer than that."""
    _, truth, snaps, _ = ramp
    longer = shortest_length(snaps) + LONGER_M
    comp = _complete(ramp, longer)
    assert int(comp.generated.sum()) > 50
    gap, floor = _bumper_gaps(ramp, comp, longer)
    assert len(gap) > 100
    assert np.all(gap >= floor - 1e-6), float((gap - floor).min())
    assert int(comp.dropped.sum()) == 0
    old = _complete(ramp, None)  # placed for the shortest, inserted LONGER_M longer
    gap_old, floor_old = _bumper_gaps(ramp, old, longer)
    assert np.any(gap_old < floor_old - 0.5), float((gap_old - floor_old).min())


def test_as_long_as_the_shortest_the_completion_is_unchanged(ramp) -> None:
    """A generated vehicle as long as the shortest recorded one (the ring, Bremen,
    netgen_corridor): the completion is the one without a length, bit for bit, and that one
    is the completion before stop 47 (its digest at 4a4958d)."""
    _, truth, snaps, _ = ramp
    assert generated_length(truth) == typical_length(truth)  # Stage II's, the same rule
    assert generated_length(truth) == pytest.approx(shortest_length(snaps))
    same = _complete(ramp, generated_length(truth))
    none = _complete(ramp, None)
    assert _digest(same) == _digest(none)
    assert _digest(none) == BEFORE_DIGEST


BEFORE_DIGEST = "95282bd115016544b7ba77d5887ed82a"  # 4a4958d, this venv's torch and SUMO
