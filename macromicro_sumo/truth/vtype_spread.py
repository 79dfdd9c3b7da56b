"""Ground truths whose standing queues do not sit on a lattice: every vType of a demand's
route files replaced by a seeded ``vTypeDistribution`` of the same id, whose members differ
in length and minGap (as SUMO's ``tools/createVehTypeDistribution.py`` builds one).

SUMO's equal cars (5 m, 2.5 m minGap) stand in a queue at fixed places: the first front
1.0 m before the line, each further car 7.5 m behind. A point loop is then either always
under a standing car (it reads 106-138 veh/km per lane against a true 86-101) or always in a
gap (30-77 against 88-118): no correction of the hidden count can be tuned on such queues
(stop 47, hQ47). Field queues mix lengths and gaps, which smears the lattice within a few
vehicles; this gives the simulated ground truth the same spread. The flows keep their
``type=``: SUMO draws a member per vehicle from its seeded random stream, the recorded
``vtype`` is the member (``sumo.demand.check_demand`` reads the members).
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from macromicro_sumo.data.vtypes import MEMBER_SEP
from macromicro_sumo.errors import UserError
from macromicro_sumo.sumo.demand import VCLASS_DEFAULT, VCLASS_DEFAULTS

SPREAD_MEMBERS = 20
"""Members per vType: enough distinct lengths that no two queued neighbours repeat a
spacing, few enough that ``vtypes.csv`` stays short."""
LENGTH_CV = 0.10
"""Standard deviation of a member's length over the vType's (passenger cars: 5 m +- 0.5 m,
the spread of a mid-size car fleet)."""
MIN_GAP_SD_M = 0.5
"""Standard deviation of a member's minGap [m] around the vType's."""
MIN_GAP_RANGE_M = (1.0, 4.0)
LENGTH_CLIP = 2.0
"""Members' lengths and minGaps are cut at this many standard deviations (no 0 m car)."""


def member_shapes(
    length_m: float, min_gap_m: float, members: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(lengths, minGaps) [m] of ``members`` members around a vType's: normal draws cut at
    ``LENGTH_CLIP`` standard deviations, then shifted so their means are the vType's own
    (the stream's mean jam spacing stays the original's), rounded to cm."""
    z = np.clip(rng.standard_normal((2, members)), -LENGTH_CLIP, LENGTH_CLIP)
    z -= z.mean(axis=1, keepdims=True)
    lengths = length_m * (1.0 + LENGTH_CV * z[0])
    lo, hi = MIN_GAP_RANGE_M
    gaps = np.clip(min_gap_m + MIN_GAP_SD_M * z[1], min(lo, min_gap_m), max(hi, min_gap_m))
    return np.round(lengths, 2), np.round(gaps, 2)


def spread_vtype(elem: ET.Element, members: int, rng: np.random.Generator) -> ET.Element:
    """The ``vTypeDistribution`` standing for the vType ``elem``: its id, ``members`` copies
    of it (every attribute and child kept) with drawn length and minGap, equally likely."""
    vid = elem.get("id", "")
    default_length, default_gap = VCLASS_DEFAULTS.get(elem.get("vClass", ""), VCLASS_DEFAULT)
    length = float(elem.get("length", default_length))
    gap = float(elem.get("minGap", default_gap))
    lengths, gaps = member_shapes(length, gap, members, rng)
    dist = ET.Element("vTypeDistribution", {"id": vid})
    width = len(str(members - 1))
    for i in range(members):
        m = copy.deepcopy(elem)
        m.tail = None
        m.set("id", f"{vid}{MEMBER_SEP}{i:0{width}d}")
        m.set("length", f"{lengths[i]:g}")
        m.set("minGap", f"{gaps[i]:g}")
        m.set("probability", "1")
        dist.append(m)
    return dist


def spread_routes(
    src: Path | str, dst: Path | str, seed: int, members: int = SPREAD_MEMBERS
) -> Path:
    """Write route file ``src`` to ``dst`` with every top-level vType replaced by its
    ``spread_vtype`` distribution, each drawn from ``seed`` in file order (the same seed, the
    same file). A vType already inside a distribution is left as it is."""
    src, dst = Path(src), Path(dst)
    if members < 2:
        raise UserError(f"vtype spread: members = {members}; accepted: at least 2")
    try:
        tree = ET.parse(src)
    except (OSError, ET.ParseError) as e:
        raise UserError(f"{src}: cannot read it as a route file ({e})") from None
    root = tree.getroot()
    rng = np.random.default_rng(seed)
    for i, elem in enumerate(list(root)):
        if elem.tag == "vType":
            dist = spread_vtype(elem, members, rng)
            dist.tail = elem.tail
            root.remove(elem)
            root.insert(i, dist)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tree.write(dst, encoding="unicode")
    return dst
