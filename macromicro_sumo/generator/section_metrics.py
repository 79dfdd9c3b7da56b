"""Stage I on a road section: how completions compare with psi's bounds and the truth.

``completion_violations`` counts the generated vehicles that break a bound (spacing,
speed, a lane the edge lacks); ``completion_metrics`` is the per-snapshot table of
generator_metrics.csv (speed and spacing statistics against psi and the true scene,
trials, projections, violations).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_sampler import SectionCompletion
from macromicro_sumo.generator.section_scene import PSI_INDEX, TOL_M, Road
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section

# --------------------------------------------------------------------------- checks, metrics


def _scene_spacings(
    lane: np.ndarray, arc: np.ndarray, section: Section
) -> tuple[np.ndarray, np.ndarray]:
    """Leader index and spacing of one scene's vehicles along the lane connections (the
    environment's leaders); NaN spacing where there is no vehicle ahead (a lane's end is
    no spacing), leader -1 there."""
    leader, sp = section_leaders(section, lane, arc)
    has = leader >= 0
    return np.where(has, leader, -1), np.where(has, sp, np.nan)


def completion_violations(
    section: Section, snaps: SectionSnapshots, comp: SectionCompletion
) -> pd.DataFrame:
    """Per snapshot, generated vehicles that break a bound: spacing below psi's minimum to
    the vehicle ahead or behind in the lane, speed outside psi's range, a lane that does
    not exist where it is (``Road.has_lane``) (``spacing``, ``speed``, ``lane`` counts)."""
    rows = []
    road = Road.of(section)
    s_min = snaps.psi[:, PSI_INDEX["spacing_min_m"]]
    v_lo, v_hi = snaps.psi[:, PSI_INDEX["speed_min_mps"]], snaps.psi[:, PSI_INDEX["speed_max_mps"]]
    for i in range(len(snaps)):
        idx = np.flatnonzero(comp.valid[i])
        gen = comp.generated[i, idx]
        lane, arc = comp.lane[i, idx], comp.arc_m[i, idx]
        leader, sp = _scene_spacings(lane, arc, section)
        close = np.nan_to_num(sp, nan=np.inf) < s_min[i] - TOL_M
        # a close pair counts against the generated vehicle at either end of it
        bad = close & gen
        bad[leader[close & ~gen]] |= gen[leader[close & ~gen]]
        v = comp.speed_mps[i, idx][gen]
        rows.append(
            {
                "spacing": int(bad.sum()),
                "speed": int(((v < v_lo[i] - 1e-9) | (v > v_hi[i] + 1e-9)).sum()),
                "lane": int(
                    (
                        ~road.has_lane(
                            torch.as_tensor(road.lane_numbers(lane[gen], arc[gen])),
                            torch.as_tensor(arc[gen]),
                        )
                    ).sum()
                ),
            }
        )
    return pd.DataFrame(rows)


def _spacing_stats(lane: np.ndarray, arc: np.ndarray, section: Section) -> tuple[float, float]:
    _, sp = _scene_spacings(lane, arc, section)
    sp = sp[np.isfinite(sp)]
    return (float(sp.mean()), float(sp.std())) if len(sp) else (np.nan, np.nan)


def completion_metrics(
    section: Section, snaps: SectionSnapshots, comp: SectionCompletion, k: np.ndarray
) -> pd.DataFrame:
    """Per snapshot: completed mean speed vs psi and truth, spacing mean/std vs truth (the
    first vehicle of a lane on an open section left out), K used vs k_true, trials,
    projections, bound violations of the generated vehicles."""
    viol = completion_violations(section, snaps, comp)
    out = []
    for i in range(len(snaps)):
        c = comp.valid[i]
        t = snaps.valid[i]
        mean_c, std_c = _spacing_stats(comp.lane[i, c], comp.arc_m[i, c], section)
        mean_t, std_t = _spacing_stats(snaps.lane[i, t], snaps.arc_m[i, t], section)
        out.append(
            {
                "run": snaps.run[i],
                "time_s": snaps.time_s[i],
                "n_observed": int((snaps.valid[i] & snaps.observed[i]).sum()),
                "k_used": int(k[i]),
                "k_true": int(snaps.k_true[i]),
                "psi_mean_speed_mps": snaps.psi[i, PSI_INDEX["mean_speed_mps"]],
                "mean_speed_mps": comp.speed_mps[i, c].mean() if c.any() else np.nan,
                "true_mean_speed_mps": snaps.speed_mps[i, t].mean() if t.any() else np.nan,
                "std_speed_mps": comp.speed_mps[i, c].std() if c.any() else np.nan,
                "true_std_speed_mps": snaps.speed_mps[i, t].std() if t.any() else np.nan,
                "psi_mean_spacing_m": snaps.psi[i, PSI_INDEX["mean_spacing_m"]],
                "mean_spacing_m": mean_c,
                "true_mean_spacing_m": mean_t,
                "psi_std_spacing_m": snaps.psi[i, PSI_INDEX["std_spacing_m"]],
                "std_spacing_m": std_c,
                "true_std_spacing_m": std_t,
                "trials": int(comp.trials[i]),
                "projections": int(comp.projections[i]),
                "dropped": 0 if comp.dropped is None else int(comp.dropped[i]),
            }
        )
    df = pd.DataFrame(out)
    df["speed_err_vs_psi_mps"] = (df["mean_speed_mps"] - df["psi_mean_speed_mps"]).abs()
    df["spacing_std_ratio"] = df["std_spacing_m"] / df["true_std_spacing_m"]
    df["violations"] = viol.sum(axis=1).to_numpy()
    df["feasible"] = df["violations"] == 0
    return df
