"""Checks of completed section scenes shared by the section generator tests, written from
SUMO's network (the section's lanes), not from the generator's own geometry."""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.section import Section


def lane_is_there(section: Section, lane: int, arc: float) -> bool:
    """Whether lane index ``lane`` exists at ``arc``, from SUMO's lanes themselves: on an
    edge its lanes; in the junction after it, the indices of the lanes that the section's
    internal lanes there lead to (a vehicle in a junction is on the lane it enters)."""
    e = int(section.edge_index(np.array([arc]))[0])
    if arc <= section.offsets_m[e] + section.lengths_m[e]:
        return lane < section.n_lanes[e]
    vias = {(v[0], v[1]) for k, v in section.lanes.items() if k.startswith(":")}
    return (e, lane) in vias
