"""What the stages exchange on a section: the recorded truth, snapshots, psi, hidden counts.

Arrays are padded to the largest fleet in the set: ``valid`` says which slots hold a
vehicle. Positions are ``(lane index, arc)`` on the section (``section.Section``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.section import Section

# psi per snapshot, from the detectors' interval that holds it (columns of ``psi``):
PSI_FIELDS = (
    "mean_speed_mps",  # space-mean speed on the section
    "mean_spacing_m",  # 1 / density per lane
    "std_spacing_m",  # spread of the spacings (NaN where the detectors cannot tell)
    "speed_min_mps",  # admissible speeds [v_min, v_max]
    "speed_max_mps",
    "spacing_min_m",  # smallest admissible front-to-front spacing (length + min gap)
)


@dataclass(frozen=True)
class SectionTruth:
    """A ground-truth folder of ``macromicro simulate`` on a section (see docs/sections.md)."""

    folder: Path
    section: Section
    trajectories: pd.DataFrame
    detectors: pd.DataFrame
    macro: pd.DataFrame
    vtypes: pd.DataFrame
    k_estimate: pd.DataFrame

    @property
    def runs(self) -> np.ndarray:
        return np.sort(self.trajectories["run"].unique())


@dataclass(frozen=True)
class SectionSnapshots:
    """Scenes on the section at snapshot times; (S, N) arrays padded with ``valid``."""

    run: np.ndarray  # (S,)
    time_s: np.ndarray  # (S,)
    lane: np.ndarray  # (S, N) int lane index
    arc_m: np.ndarray  # (S, N)
    speed_mps: np.ndarray  # (S, N)
    length_m: np.ndarray  # (S, N) vehicle lengths
    valid: np.ndarray  # (S, N) bool: a vehicle in this slot
    observed: np.ndarray  # (S, N) bool: instrumented (known to the method)
    psi: np.ndarray  # (S, len(PSI_FIELDS))
    k_true: np.ndarray  # (S,) hidden vehicles on the section (the simulation knows)
    k_est: np.ndarray  # (S,) hidden vehicles estimated from detector density

    def __len__(self) -> int:
        return len(self.run)

    @property
    def hidden(self) -> np.ndarray:
        return self.valid & ~self.observed

    def take(self, idx: np.ndarray) -> SectionSnapshots:
        return SectionSnapshots(**{f: getattr(self, f)[idx] for f in self.__dataclass_fields__})


def check_columns(df: pd.DataFrame, columns: tuple[str, ...], path: Path) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise UserError(f"{path}: missing column(s) {', '.join(missing)}")
