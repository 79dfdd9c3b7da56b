"""The ground truth's signal states along the section (``signals.csv``, ``SIGNAL_COLUMNS``).

A Stage II episode starts from a snapshot at time t of a run, in a SUMO run of its own:
its signals must show what the truth's showed at t, or a car the truth saw pass a green
light meets a red one (game/cross: 12 of 84 evaluation episodes ended in a collision at a
stop line), and the generator must know which stop lines were red or yellow at t (a
standing leader there, as for the envs' drivers; the micro pairs too). Both read this
record: per step after the warm-up and per signalised link of each lane along the section
(its own links, ``section_signal_links``), the signal's program, phase and seconds left in
the phase (what ``Simulation.set_signal_states`` puts back) and the link's stop line (lane
index, arc) with its state letter.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import SIGNAL_COLUMNS
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.simulation import Simulation


def section_signal_links(sim: Simulation, section: Section) -> list[tuple[str, int, int, float]]:
    """(signal, link index, lane index, arc of the stop line) of the signalised links of
    every lane of a section edge that has one onto the next section edge (a loop's last
    edge: its first). The stop line is the incoming edge's end, where
    ``env.section_observations.stop_points`` snaps the distances SUMO gives a driver.

    Each lane gets its own links' states, those SUMO's drivers on it meet (``getNextTLS``):
    a lane with a link onto the next section edge that link (a lane shared with a turn: the
    section's route, which its vehicles that stay on the section and the envs' driven ones
    take); a lane with none (a turning lane: its recorded vehicles turn off there) each of
    its own links, a red or yellow one of which makes its stop line a standing leader
    (``data.section.signal_stops``). A lane with no signalised link gets no row. Before,
    a turning lane got the through link's state: on game/cross the left-turn lane showed
    red in its own protected phase."""
    n = len(section.edge_ids)
    through: dict[tuple[int, int], set[tuple[str, int]]] = {}
    turns: dict[tuple[int, int], set[tuple[str, int]]] = {}
    for tls, i, src, dst, _via in sim.signal_links():
        a = section.lanes.get(src)
        if a is None or src.startswith(":") or not (section.closed or a[0] + 1 < n):
            continue
        b = None if dst.startswith(":") else section.lanes.get(dst)
        onto = b is not None and b[0] == (a[0] + 1) % n
        (through if onto else turns).setdefault((a[0], a[1]), set()).add((tls, i))
    edges = {e for e, _ in through}
    lanes = {**{k: v for k, v in turns.items() if k[0] in edges}, **through}
    ends = section.offsets_m + section.lengths_m
    return sorted((t, i, ln, float(ends[e])) for (e, ln), links in lanes.items() for t, i in links)


class SignalRecorder:
    """Collects ``signals.csv``'s rows of one run, one ``record`` per recorded step."""

    def __init__(self, sim: Simulation, section: Section) -> None:
        self.links = section_signal_links(sim, section)
        self.ids = sorted({t for t, *_ in self.links})
        self.rows: list[tuple] = []

    def record(self, sim: Simulation, time_s: float) -> None:
        if not self.links:
            return
        states = dict(zip(self.ids, sim.signal_states(self.ids), strict=True))
        for tls, i, lane, arc in self.links:
            program, phase, left, state = states[tls]
            self.rows.append((time_s, tls, program, phase, round(left, 6), lane, arc, state[i]))

    def frame(self, run: int) -> pd.DataFrame:
        df = pd.DataFrame(self.rows, columns=list(SIGNAL_COLUMNS[1:]))
        df.insert(0, "run", np.int64(run))
        return df
