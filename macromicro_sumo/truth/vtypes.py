"""vtypes.csv of a simulated ground truth: what the later stages know of each vType.

Its length and minGap (``sumo.demand``: the user's files, SUMO's vClass defaults where they
set none), its vClass and decel as SUMO drove it, its jmStoplineGap (where its drivers stop
before a red line: SUMO's default 1 m, for every carFollowModel, where the vType sets none)
and how many of its vehicles drove on the section.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from macromicro_sumo.road.leaders import STOPLINE_GAP_M
from macromicro_sumo.sumo.demand import VType


def vtype_frame(
    vtypes: dict[str, VType], vclass: dict[str, tuple[str, float]], traj: pd.DataFrame
) -> pd.DataFrame:
    """One row per vType of the demand; ``vclass``: vType -> (SUMO's vClass, decel) as the
    runs read them (a vType no run met: passenger, NaN)."""
    return pd.DataFrame(
        [
            {
                "vtype": v.id,
                "car_follow_model": v.car_follow_model,
                "vclass": vclass.get(v.id, ("passenger",))[0],
                "length_m": v.length_m,
                "min_gap_m": v.min_gap_m,
                "decel_mps2": vclass.get(v.id, ("", np.nan))[1],  # SUMO's; NaN: unknown
                "stopline_gap_m": float(v.params.get("jmStoplineGap", STOPLINE_GAP_M)),
                "vehicles": int(traj.loc[traj["vtype"] == v.id, "vehicle_id"].nunique()),
            }
            for v in vtypes.values()
        ]
    )
