"""Scenes that hide given numbers of vehicles: ``--hidden K`` of ``complete`` and ``evaluate``.

Where each snapshot draws its own hidden set (``instrumented.hidden = "snapshot"``, the
paper's ring) every snapshot with at least K vehicles is taken once per K, K random
vehicles hidden (``snapshots_by_k``, the evaluation's protocol). Elsewhere the hidden set
is the road's (the non-instrumented vehicles): the scenes kept are those that hide K,
counted by the simulation (``k_true``) or, on field data where nobody counted them, by
the detectors' estimate (``k_est``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from macromicro_sumo.data.section import (
    SectionSnapshots,
    concat_snapshots,
    hidden_per_snapshot,
    snapshots_by_k,
)
from macromicro_sumo.errors import UserError


def hidden_count(snaps: SectionSnapshots, field: bool) -> np.ndarray:
    """(S,) the number of vehicles each scene hides: the simulation's count, or on field
    data (``field``) the detectors' estimate."""
    return np.asarray(snaps.k_est if field else snaps.k_true, dtype=np.int64)


def _ranges(values: np.ndarray) -> str:
    """``1..3, 7`` for the sorted distinct values (a short list for an error line)."""
    vals = sorted({int(v) for v in values})
    parts, start = [], None
    for i, v in enumerate(vals):
        start = v if start is None else start
        if i + 1 == len(vals) or vals[i + 1] != v + 1:
            parts.append(str(v) if v == start else f"{start}..{v}")
            start = None
    return ", ".join(parts) if parts else "none"


def scenes_hiding(
    sc,
    recorded: SectionSnapshots,
    ks: Sequence[int],
    where: str,
    lowest: int = 0,
) -> tuple[SectionSnapshots, dict[int, range]]:
    """The scenes of ``recorded`` (the truth's snapshots, instrumented vehicles observed)
    that hide each K of ``ks``, one K after the other, and the scenes of each K.

    ``where`` names the ground truth in errors; ``lowest`` is the smallest K accepted
    (``evaluate``: 1, a scene hiding nothing has nothing to drive). A K outside the counts
    the scenes can hide is a one-line UserError with the accepted range."""
    ks = list(dict.fromkeys(int(k) for k in ks))  # in the given order, each once
    field = sc.data.source == "files"
    if hidden_per_snapshot(sc):
        most = int(recorded.valid.sum(axis=1).max())
        bad = [k for k in ks if not lowest <= k <= most]
        if bad:
            raise UserError(
                f"--hidden {bad[0]}: {where} holds at most {most} vehicles in a snapshot; "
                f"accepted K in [{lowest}, {most}]"
            )
        parts = snapshots_by_k(recorded, ks, sc.seed)
    else:
        counts = hidden_count(recorded, field)
        what = "estimated by the detectors" if field else "counted by the simulation"
        bad = [k for k in ks if k < lowest or not (counts == k).any()]
        if bad:
            have = counts[counts >= lowest]
            raise UserError(
                f"--hidden {bad[0]}: no scene of {where} hides {bad[0]} vehicles ({what}); "
                f"accepted: {_ranges(have)}"
            )
        parts = {k: recorded.take(np.flatnonzero(counts == k)) for k in ks}
    scenes, start, out = [], 0, {}
    for k, snaps in parts.items():
        scenes.append(snaps)
        out[k] = range(start, start + len(snaps))
        start += len(snaps)
    return concat_snapshots(scenes), out
