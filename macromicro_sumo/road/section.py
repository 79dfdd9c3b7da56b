"""A road section of any SUMO network as a 1-D coordinate per lane (pure sumolib, no SUMO run).

The section is a list of connected edges in driving order, open (a corridor with an
upstream and a downstream end) or closed (a loop). Every position on it is
``(lane index, arc)``: the lane index counts from the right as in SUMO (0 = rightmost), and
the arc runs along the section from the start of its first edge. Junctions between
consecutive edges get their own stretch of arc (the length of SUMO's internal lane), so a
vehicle crossing a junction moves on smoothly. The ring is the special case of a one-lane
closed section without internal lanes (``RingGeometry`` is what ``as_ring()`` gives back).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sumolib

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import write_json

NO_LEADER_GAP_M = 250.0  # spacing reported when nothing drives ahead on the section


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
        s = np.mod(arc_m, self.length_m) if self.closed else np.asarray(arc_m)
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
        )

    def write(self, path: Path) -> None:
        write_json(self.to_json(), path)

    @staticmethod
    def read(path: Path) -> Section:
        try:
            return Section.from_json(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise UserError(f"{path}: not a section file ({type(exc).__name__})") from None


def read_net(net_file: Path) -> sumolib.net.Net:
    """The network, with internal lanes; a file that is not a SUMO network is a UserError."""
    try:
        return sumolib.net.readNet(str(net_file), withInternal=True)
    except Exception as exc:  # sumolib raises bare parser errors
        raise UserError(f"{net_file}: not a readable SUMO network ({type(exc).__name__})") from None


def _junction(
    net_file: Path, net: Any, a: Any, b: Any
) -> tuple[float, list[tuple[str, int, float]]]:
    """Internal lanes from edge ``a`` into edge ``b``: (nominal length, [(via lane, lane
    index on b, its length)]). Raises when no lane of ``a`` leads into ``b``."""
    vias: list[tuple[str, int, float]] = []
    connected = False
    for lane in a.getLanes():
        for con in lane.getOutgoing():
            if con.getToLane().getEdge() is not b:
                continue
            connected = True
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
    net = read_net(net_file)
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
    for i, (a, b) in enumerate(pairs):
        try:
            junction[i], via_lists[i] = _junction(net_file, net, a, b)
        except UserError as exc:
            raise UserError(f"{where}: {str(exc).split(': ', 1)[1]}") from None
    offsets = np.concatenate([[0.0], np.cumsum(lengths + junction)[:-1]])
    n_lanes = np.array([e.getLaneNumber() for e in objs], dtype=np.int64)
    limits = np.full((n, int(n_lanes.max())), np.nan)
    lanes: dict[str, tuple[int, int, float, float]] = {}
    for i, e in enumerate(objs):
        for lane in e.getLanes():
            idx = lane.getIndex()
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
    )


def lane_leaders(
    lane: np.ndarray, arc_m: np.ndarray, length_m: float, closed: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Leader index (-1: none) and front-to-front spacing [m] of every vehicle, per lane.

    O(V log V) for V vehicles: one sort by (lane, arc). On an open section the first
    vehicle of a lane has no leader (spacing ``NO_LEADER_GAP_M``); on a closed one it
    follows the last vehicle of its lane around the loop.
    """
    v = len(arc_m)
    leader = np.full(v, -1, dtype=np.int64)
    spacing = np.full(v, NO_LEADER_GAP_M)
    if v == 0:
        return leader, spacing
    order = np.lexsort((arc_m, lane))
    ln, s = lane[order], arc_m[order]
    same = ln[1:] == ln[:-1]
    behind, ahead = order[:-1][same], order[1:][same]
    leader[behind] = ahead
    spacing[behind] = (s[1:] - s[:-1])[same]
    if closed:
        # Last vehicle of each lane follows that lane's first vehicle, around the loop.
        first = np.concatenate([[True], ~same])
        last = np.concatenate([~same, [True]])
        firsts, lasts = order[first], order[last]
        leader[lasts] = firsts
        spacing[lasts] = s[first] + length_m - s[last]
        alone = firsts == lasts
        spacing[lasts[alone]] = length_m
    return leader, spacing
