"""The ground truth's signal states along the section (``signals.csv``, ``SIGNAL_COLUMNS``).

A Stage II episode starts from a snapshot at time t of a run, in a SUMO run of its own:
its signals must show what the truth's showed at t, or a car the truth saw pass a green
light meets a red one (game/cross: 12 of 84 evaluation episodes ended in a collision at a
stop line), and the generator must know which stop lines were red or yellow at t (a
standing leader there, as for the envs' drivers). Both read this record: per step after
the warm-up and per signalised link along the section, the signal's program, phase and
seconds left in the phase (what ``Simulation.set_signal_states`` puts back) and the link's
stop line (lane index, arc) with its state letter.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import SIGNAL_COLUMNS
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.simulation import Simulation


def section_signal_links(sim: Simulation, section: Section) -> list[tuple[str, int, int, float]]:
    """(signal, link index, lane index, arc of the stop line) of every signalised link from
    a lane of a section edge onto the next section edge (a loop's last edge: its first). The
    stop line is the incoming edge's end, where ``env.section_bank.stop_points`` snaps the
    distances SUMO gives a driver. A lane of that edge with no link onto the next section
    edge (a turning lane: a driver on the section's route must leave it) gets the edge's
    links too: such a driver meets the signal of the lane it changes to (SUMO's
    ``getNextTLS`` along its route, what the envs read)."""
    n = len(section.edge_ids)
    out: set[tuple[str, int, int, float]] = set()
    for tls, i, src, dst, _via in sim.signal_links():
        a, b = section.lanes.get(src), section.lanes.get(dst)
        if a is None or b is None or src.startswith(":") or dst.startswith(":"):
            continue
        e = a[0]
        if b[0] == (e + 1) % n and (section.closed or e + 1 < n):
            out.add((tls, i, e, a[1]))
    for e in {x[2] for x in out}:
        own = {x[3] for x in out if x[2] == e}
        links = {x[:2] for x in out if x[2] == e}
        out |= {
            (*k, e, ln) for k in links for ln in range(int(section.n_lanes[e])) if ln not in own
        }
    ends = section.offsets_m + section.lengths_m
    return sorted((t, i, ln, float(ends[e])) for t, i, e, ln in out)


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
