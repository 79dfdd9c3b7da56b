"""SUMO's input for a drawn IDM fleet: one vType per vehicle, and routes round a closed road.

The fleet's vehicles are inserted one by one at exact positions and speeds
(``Simulation.add_vehicles``); what SUMO must know beforehand is here, as XML text.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from xml.sax.saxutils import quoteattr

import pandas as pd

FLEET_ROUTE_PREFIX = "fleet_"  # route fleet_<edge>: laps round the section from <edge>


def vtypes_xml(params: pd.DataFrame, step_length_s: float) -> str:
    """One IDM vType per vehicle (delta can only be set in XML, not at run time)."""
    rows = []
    for r in params.itertuples():
        rows.append(
            f'    <vType id="{r.vehicle_id}" carFollowModel="IDM" accel="{r.accel_mps2:.4f}" '
            f'decel="{r.decel_mps2:.4f}" emergencyDecel="9" tau="{r.tau_s:.4f}" minGap="{r.min_gap_m:.4f}" '
            f'delta="{r.delta:g}" speedFactor="{r.speed_factor:.4f}" speedDev="0" '
            f'maxSpeed="{r.max_speed_mps:.4f}" length="{r.length_m:g}" stepping="{step_length_s:g}"/>'
        )
    # stepping = step length: one Euler IDM iteration per step, as the textbook model.
    return "<additional>\n" + "\n".join(rows) + "\n</additional>\n"


def loop_laps(length_m: float, top_speed_mps: float, duration_s: float) -> int:
    """Laps a route round a loop of ``length_m`` needs so that no vehicle reaches its end
    within ``duration_s`` at ``top_speed_mps`` (two spare: the start edge and rounding)."""
    return int(math.ceil(top_speed_mps * duration_s / length_m)) + 2


def loop_routes_xml(edge_ids: Sequence[str], laps: int) -> str:
    """Route ``fleet_<edge>`` per edge of a closed section: ``laps`` laps from that edge.
    Long routes instead of the ring's rerouters: any closed section works without them."""
    n = len(edge_ids)
    rows = []
    for k, edge in enumerate(edge_ids):
        lap = [edge_ids[(k + i) % n] for i in range(n)]
        rid = quoteattr(f"{FLEET_ROUTE_PREFIX}{edge}")
        rows.append(f'    <route id={rid} edges="{" ".join(lap * laps)}"/>')
    return "<additional>\n" + "\n".join(rows) + "\n</additional>\n"
