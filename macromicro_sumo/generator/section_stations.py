"""Where along the section Stage I's generated vehicles drive: the stations' speeds.

Station speeds (``StationSpeeds``). The proposal centres each generated vehicle's speed on
the one speed the scene still needs for psi's mean (``section_model.propose``): on a
section whose speed changes along the road every generated car was pulled to the scene's
mean, not to the speed where it is (drawn 501, stop 35: 13-16 m/s generated downstream of
the bottleneck where the truth's hidden vehicles drive 19-27, 9.0 in a queue where they
stand at 3.8). Where the section has two or more detector stations with a speed in the
snapshot's interval, ``complete_section`` proposes in a detrended frame: every vehicle's
speed less ``speed_offset`` (the stations' speed, interpolated along the arc, less psi's
mean), so the proposal's mean bookkeeping is untouched, and adds the offset back where the
vehicle is placed; the kinematic checks see the real speeds.

Not wired into the pipeline (stop 36): ``complete_section(..., stations=...)`` takes it, no
stage passes it. The evaluation's completions with station speeds, each net's truth,
generator and policy of 8cb4f22 (the policy trained on the old scenes): Stage II mean-speed
error on netgen_corridor policy 0.328 -> 0.369 m/s, idm_calibrated 0.368 -> 0.317; on
drawn 501 policy 0.109 -> 0.525, idm_calibrated 1.000 -> 0.020, the policy's per-station
speed error 1.16 -> 0.58. The start scenes' speeds per 250 m follow the truth's (netgen:
RMSE 2.31 -> 0.57 m/s); the policy's error grows on both nets, so it stays off
(/work/scratch/hQ36/docs_section.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.data.section import SectionSnapshots

MIN_STATIONS = 2  # stations with a speed needed for a speed profile along the section


@dataclass(frozen=True)
class StationSpeeds:
    """Each detector interval's station speeds along the section: per run and interval the
    stations' arcs and speeds, a station's lanes pooled as the space-mean of its passages
    (sum n / sum (n / v) over lanes that counted a vehicle)."""

    table: pd.DataFrame  # run, begin_s, end_s, arc_m, speed_mps

    @classmethod
    def of(cls, detectors: pd.DataFrame) -> StationSpeeds:
        """From a ground truth's ``detectors.csv`` (``SectionTruth.detectors``)."""
        d = detectors[(detectors["n_veh"] > 0) & (detectors["speed_mps"] > 0)]
        d = d.assign(
            arc_key=d["arc_m"].round(1),
            w=d["n_veh"] / d["speed_mps"],
        )
        g = d.groupby(["run", "begin_s", "end_s", "arc_key"], as_index=False)
        t = g.agg(n=("n_veh", "sum"), w=("w", "sum"))
        t = t.assign(speed_mps=t["n"] / t["w"]).rename(columns={"arc_key": "arc_m"})
        return cls(t[["run", "begin_s", "end_s", "arc_m", "speed_mps"]])

    def profile(self, snaps: SectionSnapshots) -> tuple[np.ndarray, np.ndarray]:
        """(S, P) the stations' arcs (ascending; inf: padding) and speeds of the interval
        that holds each snapshot's (run, time); a snapshot with fewer than MIN_STATIONS
        stations gets none (no profile: the scene's mean, as before)."""
        rows: list[tuple[np.ndarray, np.ndarray]] = []
        groups = dict(tuple(self.table.groupby(["run", "begin_s", "end_s"])))
        by_run: dict[int, list[tuple[float, float, pd.DataFrame]]] = {}
        for (run, b, e), g in groups.items():
            by_run.setdefault(int(run), []).append((float(b), float(e), g.sort_values("arc_m")))
        for run, t in zip(snaps.run, snaps.time_s, strict=True):
            hit = [g for b, e, g in by_run.get(int(run), []) if b <= t < e]
            if hit and len(hit[0]) >= MIN_STATIONS:
                rows.append((hit[0]["arc_m"].to_numpy(float), hit[0]["speed_mps"].to_numpy(float)))
            else:
                rows.append((np.zeros(0), np.zeros(0)))
        p = max([len(a) for a, _ in rows] + [1])
        arcs = np.full((len(rows), p), np.inf)
        speeds = np.zeros((len(rows), p))
        for i, (a, v) in enumerate(rows):
            arcs[i, : len(a)], speeds[i, : len(a)] = a, v
            speeds[i, len(a) :] = v[-1] if len(v) else 0.0
        return arcs, speeds


def station_speed(arcs: torch.Tensor, speeds: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
    """(B, n) the stations' speed at ``arc`` (B, n): linear between the two stations around
    it, the nearest's beyond the first and last; NaN in rows without stations (``arcs``,
    ``speeds`` (B, P) as ``StationSpeeds.profile``)."""
    n_st = torch.isfinite(arcs).sum(dim=1, keepdim=True)
    x = arc.detach().contiguous()
    i = torch.searchsorted(arcs.contiguous(), x)  # stations before x
    last = (n_st - 1).clamp(min=0)
    left = (i - 1).clamp(min=0)
    left = torch.minimum(left, last)
    right = torch.minimum(i, last)
    a0, a1 = arcs.gather(1, left), arcs.gather(1, right)
    v0, v1 = speeds.gather(1, left), speeds.gather(1, right)
    span = torch.where(right > left, a1 - a0, torch.ones_like(a0))
    w = torch.where(right > left, ((x - a0) / span).clamp(0.0, 1.0), torch.zeros_like(a0))
    v = v0 + w * (v1 - v0)
    return torch.where(n_st >= MIN_STATIONS, v, torch.full_like(v, float("nan")))


def speed_offset(
    prof: tuple[torch.Tensor, torch.Tensor] | None, arc: torch.Tensor, v_mean: torch.Tensor
) -> torch.Tensor:
    """(B, n) how much faster the stations say traffic drives at ``arc`` than psi's mean
    ``v_mean`` (B,): the generator's detrending (0 without a profile)."""
    if prof is None:
        return torch.zeros_like(arc)
    v = station_speed(prof[0], prof[1], arc)
    return torch.where(torch.isfinite(v), v - v_mean[:, None], torch.zeros_like(v))


def profile_level(
    prof: tuple[torch.Tensor, torch.Tensor], arc: np.ndarray, valid: np.ndarray, v_mean: np.ndarray
) -> np.ndarray:
    """(B,) the stations' speed averaged over a completed scene's vehicles (``arc``,
    ``valid`` (B, M)); psi's mean ``v_mean`` in rows without a profile. Offsets about this
    level sum to 0 over those vehicles, so the scene's mean stays psi's wherever the
    generator put them: about psi's mean itself, a generator that puts fewer cars than the
    truth into a slow stretch made the scene fast (drawn 501: 13.45 m/s generated against
    the truth's hidden 10.64, 11.55 before the station speeds)."""
    v = station_speed(prof[0], prof[1], torch.as_tensor(arc, dtype=torch.float64)).numpy()
    ok = np.asarray(valid, dtype=bool) & np.isfinite(v)
    n = ok.sum(axis=1)
    mean = np.where(ok, v, 0.0).sum(axis=1) / np.maximum(n, 1)
    return np.where(n > 0, mean, v_mean)
