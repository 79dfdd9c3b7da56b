"""The section's typical vType: the one with the most vehicles on the section, whose
values the generated vehicles take (Stage I's placement, Stage II's environments).

A ground truth with ``truth.vtype_spread`` drives each vType of the demand as a
``vTypeDistribution`` of members (``car~00`` .. ``car~19``) whose lengths and minGaps
differ, and ``vtypes.csv`` has one row per member. The typical vehicle is then the
distribution with the most vehicles, and of its members the one nearest its mean length and
minGap: one member with the most vehicles (1161's spread copy: ``car~00``, 5.64 m and
2.82 m, against a mean of 5.00 m and 2.51 m) would give every generated vehicle that one
member's odd size, and a real member (not the mean itself) keeps the generated vehicles'
vType, length and minGap one SUMO vType (``env.section_bank``'s ``length_of`` by id).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

MEMBER_SEP = "~"
"""Between a vType's id and its member's number in a spread distribution (``car~07``,
``truth.vtype_spread``): a character SUMO ids allow and the demands seen do not use."""


def vtype_groups(ids: pd.Series) -> pd.Series:
    """Each vType's distribution: the id before its last ``MEMBER_SEP`` (a plain vType: its
    own id)."""
    return ids.astype(str).str.rsplit(MEMBER_SEP, n=1).str[0]


def typical_row(vtypes: pd.DataFrame) -> int:
    """Position of the typical vType's row: the one with the most vehicles; where members
    of spread distributions are listed (``MEMBER_SEP``), the member of the distribution with
    the most vehicles nearest its vehicle-weighted mean length and minGap (ties: the first
    in file order)."""
    n = vtypes["vehicles"].to_numpy(dtype=float)
    groups = vtype_groups(vtypes["vtype"])
    if (groups == vtypes["vtype"].astype(str)).all() or not {"length_m", "min_gap_m"} <= set(
        vtypes
    ):
        return int(np.argmax(n))
    totals = pd.Series(n).groupby(groups.to_numpy(), sort=False).sum()
    members = np.flatnonzero(groups.to_numpy() == totals.idxmax())
    w = n[members] if n[members].sum() > 0 else np.ones(len(members))
    shape = vtypes[["length_m", "min_gap_m"]].to_numpy(dtype=float)[members]
    mean = (shape * w[:, None]).sum(axis=0) / w.sum()
    return int(members[np.argmin(((shape - mean) ** 2).sum(axis=1))])


def typical(vtypes: pd.DataFrame, column: str) -> object:
    """``column`` of the typical row of ``vtypes`` (``SectionTruth.vtypes``,
    ``typical_row``)."""
    return vtypes[column].iloc[typical_row(vtypes)]
