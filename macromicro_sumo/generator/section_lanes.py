"""Stage I's lanes: one index per lane along the network's lane connections (issue 17).

The generator cuts every lane into gaps between consecutive vehicles (``section_scene``).
Where a SUMO lane index means the same lane along the section that is right; where the
through lane changes index at a junction it is not: on drawn net 501 lane 1 of a two-lane
edge continues onto lane 0 of a one-lane edge, and where an on-ramp adds a lane on the
right every through lane's index grows by one. Gaps per SUMO index then did not see two
vehicles one behind the other on the network as neighbours: the generator put cars 0.6 m
apart across the junction, or a slow car 6.5 m ahead of a fast observed one, and
``section_pairs.drop_unsafe_pairs`` dropped them afterwards (0.1-1% of the generated
vehicles on drawn 501 / 503, game/cross).

So the generator numbers its lanes along the connections (``through_lanes``): a lane keeps
the number of the lane it continues from, a lane nothing continues onto (a lane added, a
ramp's) gets a new one. The leader of a vehicle in the generator's gaps is then the one
``road.leaders.section_leaders`` finds along the connections. Where a lane fans out onto
several, it continues onto one of them (``_onto``: one that goes on along the section,
the nearest index first); the others begin as lanes of their own. Where several lanes
continue onto one (a merge), the first keeps its number and the others end there. On a
closed section, or where the numbering comes out as SUMO's own, the SUMO indices are kept
(the ring, the examples with unchanged lanes: bit for bit as before).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from macromicro_sumo.road.section import Section

END_MARGIN_M = 1e-6  # keeps a vehicle at an open downstream end strictly on the section


def through_lanes(section: Section, connections: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(``number``, ``lane``): ``number`` (E, max lanes) each SUMO lane's number along the
    connections (-1: the edge has no such lane); ``lane`` (E, V) the SUMO lane index of
    number v on each edge (-1: v is not on that edge). The identity where the section is
    closed, its connections keep every index, or ``connections`` is False (SUMO's indices)."""
    n, m = len(section.edge_ids), section.max_lanes
    exists = np.arange(m)[None, :] < section.n_lanes[:, None]
    number = np.where(exists, np.arange(m)[None, :], -1)
    if connections and not section.closed:
        nxt = int(section.n_lanes[0])
        for e in range(n - 1):
            onto = _onto(section, e)
            for j in range(int(section.n_lanes[e + 1])):
                feeders = np.flatnonzero(onto == j)
                if len(feeders):
                    number[e + 1, j] = number[e, feeders[0]]
                else:
                    number[e + 1, j], nxt = nxt, nxt + 1
    v = int(number.max()) + 1
    lane = np.full((n, v), -1, dtype=np.int64)
    for e in range(n):
        for i in range(int(section.n_lanes[e])):
            lane[e, number[e, i]] = i
    return number.astype(np.int64), lane


def fan_outs(
    section: Section, number: np.ndarray, lane: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(V,) for each lane number that begins where a lane fans out onto it (a lane of the
    edge before continues onto it and onto another, under its own number), the feeding
    lane's number (-1: none) and the arc where the new one begins (its junction included;
    inf: none). The envs' leader search takes the nearest of a fan-out's continuations
    (``section_leaders``): a vehicle at such a lane's start is the leader of the feeding
    lane's last vehicle before it, which the gaps then keep as its follower."""
    v = lane.shape[1]
    feeder = np.full(v, -1, dtype=np.int64)
    branch = np.full(v, np.inf)
    if section.closed:
        return feeder, branch
    for w in range(v):
        k = int(np.argmax(lane[:, w] >= 0))
        if k == 0:
            continue
        fed = np.flatnonzero(section.links[k - 1, :, lane[k, w]])
        if len(fed):
            feeder[w] = number[k - 1, fed[0]]
            branch[w] = float(section.node_start_m[k])
    return feeder, branch


def _onto(section: Section, e: int) -> np.ndarray:
    """(max lanes,) the lane of edge e + 1 each lane of edge e continues onto (-1: none):
    of several, one whose links reach the section's end (``_reach``: netgen_corridor's e3
    fans out onto e4 lane 0, whose only continuation ends on e5, and lane 1, the corridor's
    through lane), then one that is no turning lane (``route_ends``), the nearest index
    first, the right one of two equally near."""
    m = section.max_lanes
    out = np.full(m, -1, dtype=np.int64)
    ends = section.route_ends[e + 1]
    reach = _reach(section)[e + 1]
    for i in range(int(section.n_lanes[e])):
        targets = np.flatnonzero(section.links[e, i])
        if not len(targets):
            continue
        key = [(not reach[j], bool(ends[j]), abs(int(j) - i), int(j)) for j in targets]
        out[i] = int(targets[min(range(len(targets)), key=key.__getitem__)])
    return out


def _reach(section: Section) -> np.ndarray:
    """(E, max lanes) whether a lane's links lead on to the open section's last edge."""
    n, m = len(section.edge_ids), section.max_lanes
    reach = np.zeros((n, m), dtype=bool)
    reach[-1] = np.arange(m) < section.n_lanes[-1]
    for e in range(n - 2, -1, -1):
        reach[e] = (section.links[e] & reach[e + 1][None, :]).any(axis=1)
    return reach


def lane_pieces(section: Section, lane_of: np.ndarray | None = None) -> list[list[list[float]]]:
    """Per lane (numbered along the connections, ``section_lanes.through_lanes``: ``lane_of``
    (E, V) its SUMO index per edge; None: SUMO's indices), the [a, b) arc intervals where
    it exists: on an edge, where the edge has it; in the junction after it, where the lane
    of the next edge it is is reached from the edge (``Section.links``): a lane in a
    junction is the lane it leads to. Why not the edge's lane count there too: an edge
    whose lanes 0-1 continue onto lanes 1-2 of the next (an on-ramp joining on the right)
    has no junction lane 0, and a vehicle put there goes to lane 0 of the next edge's
    start, into whoever is there (game/cross, net 503: Stage II evaluation collisions)."""
    n = len(section.edge_ids)
    if lane_of is None:
        lane_of = np.where(
            np.arange(section.max_lanes)[None, :] < section.n_lanes[:, None],
            np.arange(section.max_lanes)[None, :],
            -1,
        )
    ends = np.append(section.offsets_m[1:], section.length_m)
    pieces: list[list[list[float]]] = [[] for _ in range(lane_of.shape[1])]

    def add(lane: int, a: float, b: float) -> None:
        p = pieces[lane]
        if p and abs(p[-1][1] - a) < 1e-9:
            p[-1][1] = b
        else:
            p.append([a, b])

    for e in range(n):
        a = float(section.offsets_m[e])
        mid = a + float(section.lengths_m[e])
        b = float(ends[e])
        into = section.links[e].any(axis=0)  # (lanes,) next-edge lanes reached from e
        if not into.any():  # no connection known: the next edge's lanes
            into = np.arange(section.max_lanes) < section.n_lanes[(e + 1) % n]
        for lane in range(lane_of.shape[1]):
            if lane_of[e, lane] >= 0:
                add(lane, a, mid)
            j = lane_of[(e + 1) % n, lane]
            if b > mid + 1e-9 and j >= 0 and into[j]:
                add(lane, mid, b)
    return pieces


@dataclass(frozen=True)
class Road:
    """What the generator needs of a ``Section``, as torch tensors (positions in float64)."""

    length_m: float
    closed: bool
    max_lanes: int
    lane_length_m: float
    offsets_m: torch.Tensor  # (E,)
    n_lanes: torch.Tensor  # (E,) int64
    limits_mps: torch.Tensor  # (E, max lanes); a lane the edge lacks has its leftmost's limit
    # per lane index: (a, b) arc intervals where that lane exists (numpy, for projection)
    lane_spans: tuple[np.ndarray, ...]
    # the same as one (lanes, P, 2) tensor, padded with empty spans; on a loop repeated
    # one and two lengths on, since a gap may run past the loop's end
    span_table: torch.Tensor
    lane_extent_m: torch.Tensor  # (lanes,) arc length on which each lane index exists
    # The generator's lanes are numbered along the lane connections (``section_lanes``):
    # ``number`` (E, SUMO lanes) each SUMO lane's, ``sumo_lane`` (E, lanes) the SUMO index
    # of each number per edge (-1: not there); ``max_lanes`` counts the numbers.
    number: np.ndarray
    sumo_lane: np.ndarray
    node_start_m: np.ndarray  # (E,) ``Section.node_start_m``: where an edge's lanes begin
    lane_rel: torch.Tensor  # (lanes,) SUMO index where each lane begins / (SUMO lanes - 1)
    # A lane that begins where another fans out onto it (``fan_outs``): that lane (-1:
    # none) and the arc where it begins (inf: none).
    feeder: torch.Tensor
    branch_m: torch.Tensor

    @classmethod
    def of(cls, section: Section, connections: bool = True) -> Road:
        """The section's road, its lanes numbered along the connections (``connections``
        False: SUMO's indices, and no fan-out followers: the gaps before 2ee18e6)."""
        number, sumo_lane = through_lanes(section, connections)
        lim = np.array(section.limits_mps, dtype=np.float64)
        n_lanes = np.asarray(section.n_lanes, dtype=np.int64)
        for e, n in enumerate(n_lanes):
            lim[e, n:] = lim[e, n - 1]
        # each number's limit on each edge: its SUMO lane's, the edge's leftmost elsewhere
        ref = np.where(sumo_lane >= 0, sumo_lane, n_lanes[:, None] - 1)
        lim = np.take_along_axis(lim, ref, axis=1)
        first = np.argmax(sumo_lane >= 0, axis=0)  # the edge where each number begins
        index = sumo_lane[first, np.arange(sumo_lane.shape[1])]
        lane_rel = index / max(section.max_lanes - 1, 1)
        feeder, branch = fan_outs(section, number, sumo_lane)
        if not connections:
            feeder, branch = np.full_like(feeder, -1), np.full_like(branch, np.inf)
        spans = [
            np.array(p, dtype=np.float64).reshape(-1, 2) for p in lane_pieces(section, sumo_lane)
        ]
        reps = 3 if section.closed else 1
        p = max(len(x) for x in spans) * reps
        table = np.zeros((len(spans), p, 2))
        for lane, x in enumerate(spans):
            rep = np.concatenate([x + k * section.length_m for k in range(reps)])
            table[lane, : len(rep)] = rep
        return cls(
            length_m=section.length_m,
            closed=section.closed,
            max_lanes=sumo_lane.shape[1],
            lane_length_m=section.lane_length_m,
            offsets_m=torch.as_tensor(np.asarray(section.offsets_m, dtype=np.float64)),
            n_lanes=torch.as_tensor(n_lanes),
            limits_mps=torch.as_tensor(lim),
            lane_spans=tuple(spans),
            lane_extent_m=torch.as_tensor([float(np.sum(x[:, 1] - x[:, 0])) for x in spans]),
            span_table=torch.as_tensor(table),
            number=number,
            sumo_lane=sumo_lane,
            node_start_m=np.asarray(section.node_start_m, dtype=np.float64),
            lane_rel=torch.as_tensor(lane_rel, dtype=torch.float64),
            feeder=torch.as_tensor(feeder),
            branch_m=torch.as_tensor(branch),
        )

    def _node(self, arc: np.ndarray) -> np.ndarray:
        """The edge whose lanes a position is on (a junction's: the next edge's, as
        ``Section.node_of``)."""
        s = np.mod(arc, self.length_m) if self.closed else np.asarray(arc, dtype=float)
        e = np.searchsorted(self.node_start_m, s, side="left") - 1
        return np.where(e < 0, len(self.node_start_m) - 1 if self.closed else 0, e)

    def lane_numbers(self, lane: np.ndarray, arc: np.ndarray) -> np.ndarray:
        """The generator's lane numbers of SUMO lane indices ``lane`` at ``arc`` (a
        snapshot's vehicles, stop lines); -1 for a lane the edge lacks."""
        lane = np.asarray(lane, dtype=np.int64)
        e = self._node(np.asarray(arc, dtype=float))
        out = self.number[e, np.clip(lane, 0, self.number.shape[1] - 1)]
        return np.where((lane >= 0) & (lane < self.number.shape[1]), out, -1)

    def sumo_lanes(self, number: np.ndarray, arc: np.ndarray) -> np.ndarray:
        """The SUMO lane indices of the generator's lane numbers at ``arc`` (its placed
        vehicles); where a number is not on that edge, the nearest SUMO lane to where it
        begins (a vehicle there is off its lane: ``completion_violations`` counts it)."""
        number = np.clip(np.asarray(number, dtype=np.int64), 0, self.max_lanes - 1)
        e = self._node(np.asarray(arc, dtype=float))
        i = self.sumo_lane[e, number]
        width = (self.number[e] >= 0).sum(axis=-1)
        guess = np.rint(self.lane_rel.numpy()[number] * max(self.number.shape[1] - 1, 1))
        return np.where(i >= 0, i, np.clip(guess, 0, width - 1)).astype(np.int64)

    def wrap(self, arc: torch.Tensor) -> torch.Tensor:
        return torch.remainder(arc, self.length_m) if self.closed else arc

    def edge(self, arc: torch.Tensor) -> torch.Tensor:
        """Edge index (the junction after an edge counts as that edge) of each position."""
        e = torch.bucketize(self.wrap(arc.detach()).contiguous(), self.offsets_m, right=True) - 1
        return e.clamp(0, len(self.offsets_m) - 1)

    def has_lane(self, lane: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
        """Whether lane index ``lane`` exists at ``arc`` (same shapes): on an edge its
        lanes, in a junction the lanes it leads to (``lane_pieces``)."""
        spans = self.span_table[lane.clamp(0, self.max_lanes - 1)]
        a = self.wrap(arc.detach())[..., None]
        inside = (spans[..., 0] <= a) & (a < spans[..., 1])
        return inside.any(dim=-1) & (lane >= 0) & (lane < self.max_lanes)

    def limit(self, lane: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
        """Speed limit [m/s] of lane ``lane`` at ``arc`` (the edge's leftmost where it lacks it)."""
        e = self.edge(arc)
        return self.limits_mps[e, lane.clamp(0, self.max_lanes - 1)]

    def place_on_lane(
        self, lane: torch.Tensor, a: torch.Tensor, room: torch.Tensor, frac: torch.Tensor
    ) -> torch.Tensor:
        """The point at share ``frac`` of the length of [a, a + room] on which ``lane``
        exists (the pieces laid end to end): a gap across a lane drop only offers the
        part where its lane is. Where the lane is nowhere in it, ``a + frac room``."""
        spans = self.span_table[lane]  # (..., P, 2)
        pa = torch.maximum(a[..., None], spans[..., 0])
        plen = (torch.minimum((a + room)[..., None], spans[..., 1]) - pa).clamp(min=0.0)
        cum = plen.cumsum(dim=-1)
        total = cum[..., -1]
        t = frac * total
        piece = (t.detach()[..., None] >= cum.detach()).sum(dim=-1, keepdim=True)
        piece = piece.clamp(max=spans.shape[-2] - 1)
        x = pa.gather(-1, piece) + (t[..., None] - (cum - plen).gather(-1, piece))
        return torch.where(total > 0, x[..., 0], a + frac * room)

    def nearest_on_lane(self, lane: int, a: float, b: float, x: float) -> float | None:
        """The point of [a, b] nearest to ``x`` where lane ``lane`` exists (None: nowhere)."""
        if b < a:
            return None
        spans = self.lane_spans[lane]
        if self.closed:  # [a, b] may run past the loop's end (a < 2 L, b < 3 L)
            spans = np.concatenate([spans + k * self.length_m for k in range(3)])
        lo = np.maximum(spans[:, 0], a)
        hi = np.minimum(spans[:, 1] - END_MARGIN_M, b)
        ok = lo <= hi
        if not ok.any():
            return None
        near = np.clip(x, lo[ok], hi[ok])
        return float(near[np.argmin(np.abs(near - x))])
