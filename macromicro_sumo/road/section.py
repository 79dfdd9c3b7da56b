"""A road section of any SUMO network as a 1-D coordinate per lane (pure sumolib, no SUMO run).

The section is a list of connected edges in driving order, open (a corridor with an
upstream and a downstream end) or closed (a loop). Every position on it is
``(lane index, arc)``: the lane index counts from the right as in SUMO (0 = rightmost), and
the arc runs along the section from the start of its first edge. Junctions between
consecutive edges get their own stretch of arc (the length of SUMO's internal lane), so a
vehicle crossing a junction moves on smoothly. The ring is the special case of a one-lane
closed section without internal lanes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import write_json
from macromicro_sumo.sumo.inputs import read_net

NO_LEADER_GAP_M = 250.0  # spacing reported when nothing drives ahead on the section
STOP = -2  # leader index of a standing obstacle: a lane's end, or a red light's stop line


@dataclass(frozen=True)
class Section:
    """Edges in driving order and where each of their lanes sits on the arc."""

    edge_ids: tuple[str, ...]
    closed: bool
    offsets_m: np.ndarray  # (E,) arc where each edge starts
    lengths_m: np.ndarray  # (E,) edge length (its rightmost lane)
    junction_m: np.ndarray  # (E,) internal-lane length after each edge (0 for an open end)
    n_lanes: np.ndarray  # (E,) lanes per edge
    limits_mps: np.ndarray  # (E, max lanes) speed limit per edge and lane (NaN: no lane)
    # lane ID -> (edge index, lane index, arc of the lane's start, arc per lane metre);
    # internal lanes of the section's junctions are in here too.
    lanes: dict[str, tuple[int, int, float, float]] = field(repr=False)
    # (E, max lanes, max lanes) bool: lane i of edge e continues onto lane j of the next
    # section edge (a loop's last edge: its first), from the network's connections. None
    # (a section file written before connections were kept): lane i onto lane i.
    links: np.ndarray | None = field(default=None, repr=False)
    # (E, max lanes) bool: the lane leads nowhere (no connection at all): its end is a
    # standing obstacle to whoever drives on it (an on-ramp's acceleration lane, a lane drop).
    lane_ends: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.lane_ends is None:
            ends = np.zeros((len(self.edge_ids), int(self.n_lanes.max())), dtype=bool)
            object.__setattr__(self, "lane_ends", ends)
        if self.links is None:
            n, m = len(self.edge_ids), int(self.n_lanes.max())
            links = np.zeros((n, m, m), dtype=bool)
            for e in range(n if self.closed else n - 1):
                nxt = int(self.n_lanes[(e + 1) % n])
                for i in range(int(self.n_lanes[e])):
                    links[e, i, min(i, nxt - 1)] = True
            object.__setattr__(self, "links", links)

    @cached_property
    def route_ends(self) -> np.ndarray:
        """(E, max lanes) bool: the lane ends for a vehicle that drives the section's route
        (the envs' and the generator's vehicles): besides ``lane_ends``, every lane with no
        link onto the next section edge (a turning lane; an open section's last edge
        excepted), at whose end SUMO stops such a vehicle that has not left it. A recorded
        vehicle drives its own route: a turner leaves the section there."""
        exists = np.arange(self.max_lanes)[None, :] < self.n_lanes[:, None]
        ends = ~self.links.any(axis=-1) & exists
        if not self.closed:
            ends[-1] = False
        return ends | self.lane_ends

    def chain_beyond_m(self, ends: np.ndarray) -> np.ndarray:
        """(E, max lanes) arc from each lane's end to where a driver on it must have left
        it, for lane ends ``ends`` (``lane_ends``, ``route_ends``): 0 on an ending lane, on
        a lane all of whose links lead onto lanes that end (netgen_corridor: e4 lane 0 onto
        e5 lanes 0-1) the end of the chain, the farthest of them (SUMO's best lanes); inf
        where the lane carries it on."""
        n = len(self.edge_ids)
        out = np.where(ends, 0.0, np.inf)
        for _ in range(2 if self.closed else 1):  # a loop: twice round
            for e in reversed(range(n if self.closed else n - 1)):
                k = (e + 1) % n
                via = np.where(self.links[e], out[k][None, :] + self.node_span_m[k], -np.inf)
                far = via.max(axis=1, initial=-np.inf)
                chained = self.links[e].any(axis=1) & ~ends[e] & (far < np.inf)
                out[e] = np.where(chained, far, out[e])
        return out

    @cached_property
    def end_beyond_m(self) -> tuple[np.ndarray, np.ndarray]:
        """``chain_beyond_m`` of ``lane_ends`` (every vehicle) and of ``route_ends`` (a
        vehicle on the section's route)."""
        return self.chain_beyond_m(self.lane_ends), self.chain_beyond_m(self.route_ends)

    @property
    def length_m(self) -> float:
        """Arc length of the section (a loop includes its closing junction)."""
        return float(self.offsets_m[-1] + self.lengths_m[-1] + self.junction_m[-1])

    @property
    def max_lanes(self) -> int:
        return int(self.n_lanes.max())

    @property
    def lane_length_m(self) -> float:
        """Total lane length [m], junctions included (vehicles crossing them count too):
        the denominator of a density given per lane."""
        return float(((self.lengths_m + self.junction_m) * self.n_lanes).sum())

    @cached_property
    def node_start_m(self) -> np.ndarray:
        """(E,) arc where each edge's lanes begin for their drivers: the junction before an
        edge belongs to it (a vehicle inside a junction is on the lane it enters)."""
        end = self.offsets_m + self.lengths_m
        start = np.roll(end, 1)
        start[0] = end[-1] - self.length_m if self.closed else 0.0
        return start

    @cached_property
    def node_span_m(self) -> np.ndarray:
        """(E,) arc length of each edge's stretch, the junction before it included."""
        return self.offsets_m + self.lengths_m - self.node_start_m

    def wrap(self, arc_m: np.ndarray) -> np.ndarray:
        """Arc positions (or arc differences) on the section: modulo its length on a loop, as
        they are on an open section."""
        return np.mod(arc_m, self.length_m) if self.closed else arc_m

    def node_of(self, arc_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(edge index, arc from that edge's stretch start) of arc positions; a position
        inside a junction belongs to the edge after it."""
        n = len(self.edge_ids)
        s = np.asarray(self.wrap(arc_m), dtype=float)
        e = self.edge_index(s)
        inside = (s > self.offsets_m[e] + self.lengths_m[e]) & (self.closed | (e + 1 < n))
        ne = np.where(inside, (e + 1) % n, e)
        rel = s - self.node_start_m[ne]
        return ne, self.wrap(rel)

    def next_lane(self, edge: np.ndarray, lane: np.ndarray) -> np.ndarray:
        """The lane of the next section edge that ``lane`` of ``edge`` continues onto (its
        rightmost connection); the same index, clipped, where it continues nowhere."""
        e = np.asarray(edge, dtype=np.int64)
        i = np.minimum(np.asarray(lane, dtype=np.int64), self.n_lanes[e] - 1)
        row = self.links[e, i]
        nxt = (e + 1) % len(self.edge_ids)
        return np.where(row.any(axis=-1), row.argmax(axis=-1), np.minimum(i, self.n_lanes[nxt] - 1))

    def lookahead(
        self, lane: np.ndarray, arc_m: np.ndarray, edge: np.ndarray, own_limit: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The look-ahead features of vehicles on ``lane`` of ``edge`` at ``arc_m``: the next
        edge's limit on the lane each continues onto and the distance to that edge's start;
        on an open section's last edge its ``own_limit`` and the distance to the end."""
        n_e = len(self.edge_ids)
        s = self.wrap(arc_m)
        # The lane it continues onto (an on-ramp shifts the through lanes' indices); inside a
        # junction a vehicle's lane index is already the one it enters.
        inside = s > self.offsets_m[edge] + self.lengths_m[edge]
        onto = np.where(inside, lane, self.next_lane(edge, lane))
        nxt = (edge + 1) % n_e if self.closed else np.minimum(edge + 1, n_e - 1)
        next_limit = self.limits_mps[nxt, np.minimum(onto, self.n_lanes[nxt] - 1)]
        if self.closed:
            start = self.offsets_m[nxt] + np.where(nxt == 0, self.length_m, 0.0)
            return next_limit, start - s
        last = edge == n_e - 1
        limit = np.where(last, own_limit, next_limit)
        return limit, np.where(last, self.length_m, self.offsets_m[nxt]) - s

    def ahead_of_lanes(
        self, first_idx: np.ndarray, first_rel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per lane (E * max lanes, edge-major): the first item met downstream of the lane's
        end along its connections, and its arc distance from that end (-1, inf: none).

        ``first_idx`` / ``first_rel``: per lane, the item nearest its start (-1: none) and
        its arc from the start. Where a lane continues onto several, the nearest item wins
        (the cautious reading of a fan-out). A loop needs two passes round.
        """
        n, m = len(self.edge_ids), self.max_lanes
        fi, fr = first_idx.reshape(n, m), first_rel.reshape(n, m)
        idx = np.full((n, m), -1, dtype=np.int64)
        off = np.full((n, m), np.inf)
        rows = np.arange(m)
        for _ in range(2 if self.closed else 1):
            for e in reversed(range(n if self.closed else n - 1)):
                k = (e + 1) % n
                c_off = np.where(fi[k] >= 0, fr[k], off[k] + self.node_span_m[k])
                c_idx = np.where(fi[k] >= 0, fi[k], idx[k])
                cand = np.where(self.links[e], c_off[None, :], np.inf)
                j = cand.argmin(axis=1)
                best = cand[rows, j]
                ok = np.isfinite(best)
                off[e] = np.where(ok, best, np.inf)
                idx[e] = np.where(ok, c_idx[j], -1)
        return idx.ravel(), off.ravel()

    @property
    def edge_lane_ids(self) -> list[list[str]]:
        """The lane IDs of every edge, rightmost first."""
        out: list[list[str]] = [[] for _ in self.edge_ids]
        for lane, (e, _i, _, _) in self.lanes.items():
            if not lane.startswith(":"):
                out[e].append(lane)
        return [sorted(x, key=lambda lid: self.lanes[lid][1]) for x in out]

    def locate(self, lane_id: str, pos_m: float) -> tuple[int, float] | None:
        """(lane index, arc) of a SUMO lane position, or None off the section."""
        hit = self.lanes.get(lane_id)
        if hit is None:
            return None
        _, lane, start, scale = hit
        return lane, start + pos_m * scale

    def edge_index(self, arc_m: np.ndarray) -> np.ndarray:
        """Index of the edge (or the junction after it) holding each arc position."""
        s = np.asarray(self.wrap(arc_m))
        return np.clip(
            np.searchsorted(self.offsets_m, s, side="right") - 1, 0, len(self.edge_ids) - 1
        )

    def to_lane(self, lane: int, arc_m: float) -> tuple[int, int, float]:
        """(edge index, lane index, lane position) where SUMO can put (lane, arc).

        A position inside a junction goes to the start of the next edge: a lane index in
        a junction is the index of the lane it leads to, and the same index on the edge
        before may be a lane that ends there (an on-ramp's acceleration lane). A lane index
        the edge does not have goes to its leftmost lane.
        """
        s = float(np.mod(arc_m, self.length_m)) if self.closed else float(arc_m)
        e = int(self.edge_index(np.array([s]))[0])
        pos = s - float(self.offsets_m[e])
        if pos > self.lengths_m[e] and (self.closed or e + 1 < len(self.edge_ids)):
            e, pos = (e + 1) % len(self.edge_ids), 0.0
        pos = min(max(pos, 0.0), float(self.lengths_m[e]) - 0.01)
        return e, min(int(lane), int(self.n_lanes[e]) - 1), pos

    def to_json(self) -> dict[str, Any]:
        return {
            "edge_ids": list(self.edge_ids),
            "closed": self.closed,
            "offsets_m": self.offsets_m.tolist(),
            "lengths_m": self.lengths_m.tolist(),
            "junction_m": self.junction_m.tolist(),
            "n_lanes": self.n_lanes.tolist(),
            "limits_mps": np.where(np.isnan(self.limits_mps), -1.0, self.limits_mps).tolist(),
            "lanes": {k: list(v) for k, v in self.lanes.items()},
            "links": np.asarray(self.links, dtype=np.int64).tolist(),
            "lane_ends": np.asarray(self.lane_ends, dtype=np.int64).tolist(),
            "length_m": self.length_m,
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> Section:
        lim = np.array(d["limits_mps"], dtype=float)
        return Section(
            edge_ids=tuple(d["edge_ids"]),
            closed=bool(d["closed"]),
            offsets_m=np.array(d["offsets_m"], dtype=float),
            lengths_m=np.array(d["lengths_m"], dtype=float),
            junction_m=np.array(d["junction_m"], dtype=float),
            n_lanes=np.array(d["n_lanes"], dtype=np.int64),
            limits_mps=np.where(lim < 0, np.nan, lim),
            lanes={
                k: (int(v[0]), int(v[1]), float(v[2]), float(v[3])) for k, v in d["lanes"].items()
            },
            links=np.array(d["links"], dtype=bool) if "links" in d else None,
            lane_ends=np.array(d["lane_ends"], dtype=bool) if "lane_ends" in d else None,
        )

    def write(self, path: Path) -> None:
        write_json(self.to_json(), path)

    @staticmethod
    def read(path: Path) -> Section:
        try:
            return Section.from_json(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise UserError(f"{path}: not a section file ({type(exc).__name__})") from None


def _junction(
    net_file: Path, net: Any, a: Any, b: Any, links: np.ndarray
) -> tuple[float, list[tuple[str, int, float]]]:
    """Internal lanes from edge ``a`` into edge ``b``: (nominal length, [(via lane, lane
    index on b, its length)]); ``links[i, j]`` set where lane i of ``a`` continues onto
    lane j of ``b``. Raises when no lane of ``a`` leads into ``b``."""
    vias: list[tuple[str, int, float]] = []
    connected = False
    for lane in a.getLanes():
        for con in lane.getOutgoing():
            if con.getToLane().getEdge() is not b:
                continue
            connected = True
            links[lane.getIndex(), con.getToLane().getIndex()] = True
            via = con.getViaLaneID()
            if via:
                vias.append((via, con.getToLane().getIndex(), net.getLane(via).getLength()))
    if not connected:
        raise UserError(
            f"{net_file}: section edges {a.getID()!r} -> {b.getID()!r} are not connected "
            "(no lane of the first leads into the second)"
        )
    nominal = float(np.median([v[2] for v in vias])) if vias else 0.0
    return nominal, vias


def read_section(net_file: Path, edges: list[str], closed: bool, where: str = "") -> Section:
    """Build the section from the network; errors name the file and the offending edge."""
    net = read_net(net_file, with_internal=True)
    where = where or str(net_file)
    objs = []
    for eid in edges:
        if not net.hasEdge(eid):
            raise UserError(f"{where}: section edge {eid!r} is not in {net_file}")
        e = net.getEdge(eid)
        if e.getFunction() == "internal":
            raise UserError(f"{where}: section edge {eid!r} is an internal junction edge")
        objs.append(e)
    n = len(objs)
    pairs = [(objs[i], objs[i + 1]) for i in range(n - 1)]
    if closed:
        pairs.append((objs[-1], objs[0]))
    lengths = np.array([e.getLanes()[0].getLength() for e in objs], dtype=float)
    junction = np.zeros(n)
    via_lists: list[list[tuple[str, int, float]]] = [[] for _ in objs]
    width = max(e.getLaneNumber() for e in objs)
    links = np.zeros((n, width, width), dtype=bool)
    for i, (a, b) in enumerate(pairs):
        try:
            junction[i], via_lists[i] = _junction(net_file, net, a, b, links[i])
        except UserError as exc:
            raise UserError(f"{where}: {str(exc).split(': ', 1)[1]}") from None
    offsets = np.concatenate([[0.0], np.cumsum(lengths + junction)[:-1]])
    n_lanes = np.array([e.getLaneNumber() for e in objs], dtype=np.int64)
    limits = np.full((n, int(n_lanes.max())), np.nan)
    lanes: dict[str, tuple[int, int, float, float]] = {}
    lane_ends = np.zeros((n, width), dtype=bool)
    for i, e in enumerate(objs):
        for lane in e.getLanes():
            idx = lane.getIndex()
            lane_ends[i, idx] = not lane.getOutgoing() and (closed or i + 1 < n)
            limits[i, idx] = lane.getSpeed()
            scale = lengths[i] / lane.getLength() if lane.getLength() > 0 else 1.0
            lanes[lane.getID()] = (i, idx, float(offsets[i]), float(scale))
        for via, to_idx, vlen in via_lists[i]:
            scale = junction[i] / vlen if vlen > 0 else 1.0
            lanes.setdefault(via, (i, to_idx, float(offsets[i] + lengths[i]), float(scale)))
    return Section(
        edge_ids=tuple(e.getID() for e in objs),
        closed=closed,
        offsets_m=offsets,
        lengths_m=lengths,
        junction_m=junction,
        n_lanes=n_lanes,
        limits_mps=limits,
        lanes=lanes,
        links=links,
        lane_ends=lane_ends,
    )
