"""Stage I's pair check with the generated vehicles' length (``complete_section``'s
``generated_length_m``).

psi's smallest spacing is the shortest recorded vehicle plus the minimum gap. A generated car
is as long as the section's typical vehicle, so where that is longer (4.5 m IDM cars and 5 m
Krauss cars on the drawn motorways) a generated leader placed at psi's spacing in a junction
left a moving follower less than its minGap in SUMO: on fresh motorway 1169 SUMO's link
stopped an observed car at the junction from 18.5 m/s and the car behind ran into it (stop
46). On a lane, and behind a standing follower, psi's spacing holds, as before.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_pairs import drop_unsafe_pairs
from macromicro_sumo.generator.section_sampler import junction_extra

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_section_connections import build  # noqa: E402
from test_section_pairs import completion  # noqa: E402

S_MIN = 6.5  # a 4.5 m car and 2.0 m of gap
BRAKE, REACTION = 4.5, 0.5


@pytest.fixture(scope="module")
def fan_out(tmp_path_factory):
    return build(tmp_path_factory.mktemp("fan_out"), "fan_out")


def _snaps(n_observed: int) -> SectionSnapshots:
    """One snapshot of ``n_observed`` recorded vehicles, the shortest 4.5 m (psi's spacing)."""
    n = n_observed
    return SectionSnapshots(
        run=np.zeros(1, dtype=int),
        time_s=np.zeros(1),
        lane=np.zeros((1, n), dtype=np.int64),
        arc_m=np.zeros((1, n)),
        speed_mps=np.zeros((1, n)),
        length_m=np.array([[4.5] + [5.0] * (n - 1)]),
        valid=np.ones((1, n), dtype=bool),
        observed=np.ones((1, n), dtype=bool),
        psi=np.array([[14.0, 60.0, np.nan, 5.0, 20.0, S_MIN, np.inf, S_MIN]]),
        k_true=np.ones(1, dtype=int),
        k_est=np.ones(1, dtype=int),
    )


def _check(sec, follower_arc: float, follower_v: float, leader_arc: float, length) -> int:
    """Drops of a pair: an observed follower on lane 0, a generated 5 m leader on lane 1
    (in the junction: the fan-out's other internal lane) at 21 m/s."""
    comp = completion([0, 1], [follower_arc, leader_arc], [follower_v, 21.0], [False, True])
    snaps = _snaps(1)
    extra = np.concatenate([np.zeros((1, 1)), junction_extra(sec, snaps, comp, length)], 1)
    args = (sec, np.array([S_MIN]), BRAKE, REACTION, extra, None)
    return int(drop_unsafe_pairs(comp, *args)[0])


def test_a_generated_leader_in_the_junction_keeps_its_length_of_room(fan_out) -> None:
    sec = fan_out
    j0 = float(sec.offsets_m[0] + sec.lengths_m[0])  # the junction's start
    b0 = float(sec.offsets_m[1])
    assert b0 - j0 > 5.0
    # 1169's pair: the follower 1.0 m before the junction at 18.5 m/s, the leader 6.6 m
    # ahead (1.6 m of gap behind a 5 m car, less than minGap 2.0): dropped with the length,
    # kept without it (psi's 6.5 m).
    assert _check(sec, j0 - 1.0, 18.5, j0 + 5.6, 5.0) == 1
    assert _check(sec, j0 - 1.0, 18.5, j0 + 5.6, None) == 0
    # 7.1 m ahead (2.1 m of gap): kept.
    assert _check(sec, j0 - 1.5, 18.5, j0 + 5.6, 5.0) == 0
    # A standing follower may stand closer: kept.
    assert _check(sec, j0 - 1.0, 0.0, j0 + 5.6, 5.0) == 0
    # The same spacing on B's lanes, away from the junction: psi's spacing holds, kept.
    comp = completion([1, 1], [b0 + 100.0, b0 + 106.6], [18.5, 21.0], [False, True])
    assert not junction_extra(sec, _snaps(1), comp, 5.0).any()
