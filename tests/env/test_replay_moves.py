"""Recorded lane changes in Stage II's replay: a move waits while its place is taken, also
where the one who takes it had its own recorded move refused.

Drawn net 503: an observed truck's recorded change from lane 1 to lane 2 waited (a
generated car beside it), and an observed car's recorded change into lane 1, behind where
the truck would have gone, was applied anyway: judged with every move done, the truck was
gone. The car was put into the truck's side (Stage II evaluation collisions with the
record's own vehicles, steps 3-7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import sumo

from macromicro_sumo.env.section_replay import safe_places
from macromicro_sumo.road.section import read_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"


def test_a_move_into_a_place_whose_vehicle_stayed_waits() -> None:
    """On 1si (three lanes), all standing: car 0 (lane 0, 100 m) to lane 1; truck 1 (12 m,
    lane 1, 107 m) to lane 2, where car 2 stands at 108 m. The truck's move is refused, so
    the car's is too (its front would be inside the truck); with car 2 gone both go."""
    sec = read_section(CROSS, ["1fi", "1si", "2o", "2fo"], False)
    lane = np.array([0, 1, 2])
    arc = np.array([100.0, 107.0, 108.0])
    speed = np.zeros(3)
    length = np.array([4.5, 12.0, 5.0])
    args = (np.array([0, 1]), np.array([1, 2]), np.array([100.0, 107.0]), 0.5, -4.5, 2.0)
    ok = safe_places(sec, lane, arc, speed, length, *args)
    np.testing.assert_array_equal(ok, [False, False])
    away = np.array([0, 1, 1])  # car 2 on lane 1, far ahead: the truck's place is free
    ok = safe_places(sec, away, np.array([100.0, 107.0, 170.0]), speed, length, *args)
    np.testing.assert_array_equal(ok, [True, True])
