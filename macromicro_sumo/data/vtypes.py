"""The section's typical vType: the one with the most vehicles on the section, whose
values the generated vehicles take (Stage I's placement, Stage II's environments)."""

from __future__ import annotations

import numpy as np
import pandas as pd


def typical(vtypes: pd.DataFrame, column: str) -> object:
    """``column`` of the row of ``vtypes`` (``SectionTruth.vtypes``) with the most vehicles."""
    return vtypes[column].iloc[int(np.argmax(vtypes["vehicles"].to_numpy()))]
