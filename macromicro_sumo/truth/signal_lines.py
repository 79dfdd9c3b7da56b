"""A section's signalled stop lines and their fixed-time programs (the net file's
``tlLogic``; field users have them too): where each stands on the section and when the
section's lanes may pass it. ``signal_counts`` counts the approaches to them. The programs'
clock is taken as the data's (a simulation's: SUMO's).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.net_xml import NetLinks, net_links

PASSING_STATES = frozenset("GgyYs")
"""A link's states in which vehicles cross the stop line (green, yellow: those that cannot
stop pass)."""


@dataclass(frozen=True)
class StopLine:
    """A signal's stop line on the section and when the section's lanes may pass it."""

    arc_m: float
    offset_s: float
    durations_s: tuple[float, ...]  # the program's phases
    passing: tuple[bool, ...]  # per phase: some link along the section passes

    def green_s(self, t: np.ndarray) -> np.ndarray:
        """Seconds of passing from the program's origin to each of ``t`` (cumulative)."""
        d = np.array(self.durations_s, dtype=float)
        g = np.where(self.passing, d, 0.0)
        ends, cum_g = np.cumsum(d), np.concatenate([[0.0], np.cumsum(g)])
        cycle = float(ends[-1])
        x = np.asarray(t, dtype=float) - self.offset_s  # SUMO: a positive offset delays
        n, pos = np.floor(x / cycle), np.mod(x, cycle)
        k = np.clip(np.searchsorted(ends, pos, side="right"), 0, len(d) - 1)
        start = ends[k] - d[k]
        within = np.where(np.array(self.passing)[k], pos - start, 0.0)
        return n * cum_g[-1] + cum_g[k] + within

    def green_starts(self, begin_s: float, end_s: float) -> list[tuple[float, float]]:
        """Each start of passing in [``begin_s``, ``end_s``) and the stopping seconds (the
        red and the yellow the section's lanes stop at) just before it."""
        d, p = np.array(self.durations_s, dtype=float), self.passing
        starts, cycle = np.concatenate([[0.0], np.cumsum(d)[:-1]]), float(d.sum())
        out = []
        first = int(np.floor((begin_s - self.offset_s) / cycle)) - 1
        for n in range(first, int(np.ceil((end_s - self.offset_s) / cycle)) + 1):
            for k in (k for k in range(len(d)) if p[k] and not p[k - 1]):
                t = self.offset_s + n * cycle + float(starts[k])
                red, j = 0.0, k - 1
                while not p[j % len(d)]:
                    red, j = red + float(d[j % len(d)]), j - 1
                if begin_s <= t < end_s:
                    out.append((t, red))
        return sorted(out)


def _signal_links(net: NetLinks) -> dict[tuple[str, str], list[tuple[str, int]]]:
    """{(from edge, to edge): [(tls id, link index), ...]} of the net's signalled
    connections."""
    links: dict[tuple[str, str], list[tuple[str, int]]] = {}
    for c in net.connections:
        if c.tl:
            links.setdefault((c.src, c.dst), []).append((c.tl, c.link_index))
    return links


def stop_lines(net_file: Path, section: Section) -> list[StopLine]:
    """The section's signalled stop lines (fixed-time programs), in arc order: one per
    section edge whose links along the section (to the next section edge; the last edge:
    any) are signalled."""
    net = net_links(Path(net_file))
    programs, links = net.programs, _signal_links(net)
    out = []
    for e, eid in enumerate(section.edge_ids):
        nxt = section.edge_ids[e + 1] if e + 1 < len(section.edge_ids) else None
        own = [
            x for (a, b), xs in links.items() if a == eid and (nxt is None or b == nxt) for x in xs
        ]
        ids = {tl for tl, _ in own}
        if len(ids) != 1 or next(iter(ids)) not in programs:
            continue
        program = programs[next(iter(ids))]
        idx = [i for _, i in own]
        passing = tuple(
            any(i < len(s) and s[i] in PASSING_STATES for i in idx) for s in program.states
        )
        if not program.durations_s or not any(passing) or all(passing):
            continue
        arc = float(section.offsets_m[e] + section.lengths_m[e])
        out.append(StopLine(arc, program.offset_s, program.durations_s, passing))
    return out
