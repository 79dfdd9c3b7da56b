"""Reading a SUMO net file for what neither libsumo nor sumolib gives (lane stopOffsets,
which edges reach a signal, the signals' links and programs): the file opened gzip or
plain, and each reader run once per file and process, again where the file changed (its
mtime or size)."""

from __future__ import annotations

import functools
import gzip
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TypeVar

T = TypeVar("T")


def open_net(net_file: str) -> IO[bytes]:
    """``net_file`` opened for binary reading, through gzip where it ends in ``.gz``."""
    return gzip.open(net_file, "rb") if net_file.endswith(".gz") else open(net_file, "rb")


def once_per_file(read: Callable[[str], T]) -> Callable[[Path], T]:
    """``read(net_file)`` cached per (path, mtime, size): a process reads each net once."""
    cached = functools.cache(lambda path, _mtime_ns, _size: read(path))

    @functools.wraps(read)
    def per_file(net_file: Path) -> T:
        st = Path(net_file).stat()
        return cached(str(net_file), st.st_mtime_ns, st.st_size)

    return per_file


@dataclass(frozen=True)
class Connection:
    """A net file ``<connection>``: from edge, to edge, the internal lane it runs through
    (``via``, "" where none), its signal (``tl``, "" where none) and link index (-1)."""

    src: str
    dst: str
    via: str
    tl: str
    link_index: int


@dataclass(frozen=True)
class Program:
    """A signal's first ``<tlLogic>`` in the file: its offset and each phase's duration and
    state string."""

    offset_s: float
    durations_s: tuple[float, ...]
    states: tuple[str, ...]


@dataclass(frozen=True)
class NetLinks:
    """What the net file says of its links: each edge's lanes (internal edges included), the
    ``<connection>``s in file order and each signal's first program."""

    lanes: dict[str, tuple[str, ...]]
    connections: tuple[Connection, ...]
    programs: dict[str, Program]


@once_per_file
def net_links(net_file: str) -> NetLinks:
    """``net_file``'s edges' lanes, connections and signal programs (``NetLinks``), in one
    pass; read once per file and process, again where the file changed."""
    lanes: dict[str, list[str]] = {}
    connections: list[Connection] = []
    programs: dict[str, tuple[float, list[float], list[str]]] = {}
    edge, current = "", None
    with open_net(net_file) as fh:
        for event, el in ET.iterparse(fh, events=("start", "end")):
            if event == "start":
                if el.tag == "edge":
                    edge = el.get("id", "")
                    lanes.setdefault(edge, [])
                elif el.tag == "lane" and edge:
                    lanes[edge].append(el.get("id", ""))
                elif el.tag == "tlLogic" and el.get("id", "") not in programs:
                    current = el.get("id", "")
                    programs[current] = (float(el.get("offset", "0")), [], [])
                elif el.tag == "phase" and current is not None:
                    programs[current][1].append(float(el.get("duration", "0")))
                    programs[current][2].append(el.get("state", ""))
                continue
            if el.tag == "edge":
                edge = ""
            elif el.tag == "tlLogic":
                current = None
            elif el.tag == "connection":
                connections.append(
                    Connection(
                        el.get("from", ""),
                        el.get("to", ""),
                        el.get("via", "") or "",
                        el.get("tl", "") or "",
                        int(el.get("linkIndex", -1)),
                    )
                )
            if el.tag in ("edge", "connection", "tlLogic", "junction"):
                el.clear()
    return NetLinks(
        {e: tuple(ls) for e, ls in lanes.items()},
        tuple(connections),
        {k: Program(o, tuple(d), tuple(s)) for k, (o, d, s) in programs.items()},
    )
