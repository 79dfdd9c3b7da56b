"""The Krauss prior's relaxation time where the observed pairs leave it at its bound.

The free term min(a, (V - v) / T) closes a gap to the desired speed within T. The
recorded pairs decide T only where they show drivers far below their desired speed; on
ring_two_lane (recorded after the warm-up, steady traffic) none of 10,183 pairs shows free
acceleration, and the fit leaves T at its bound, 10 s (``evaluation.krauss_fit``): the
fleet, departing standing, then closes on its desired speed with a 10 s time constant and
the deployment's first minute ran 0.7-0.8 m/s slow (docs/deploy.md, "ring_two_lane's
cruise (stop 31)").

``choose_relax`` decides such a T from what the pairs do not show: the start. It drives
the demand of the runs Stage II trains on (``env.demand``'s demand episodes; never the
held-out runs) from SUMO's first step on, the population driven by the prior alone as a
deployment drives it, for each of ``RELAX_CANDIDATES_S``; reads the truth's induction
loops (``detectors.csv``: lane and arc) off the simulated vehicles that pass them; and
keeps the T whose vehicle counts per interval are closest to the truth's over the warm-up
and the ``RELAX_SCORE_S`` after it (``choose_relax`` says why counts). Stage II's own
r_macro cannot decide it: its targets (psi) start after the warm-up, when the start is
over. Measured (docs/deploy.md, "ring_two_lane's start (stop 31)"): ring_two_lane and
netgen_corridor 10 -> 5 s, game/ramp 10 -> 3 s; highway_bremen's fit identifies T (0.59 s)
and is left alone.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.env.demand import DemandCore
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.policy.demand_rollout import prior_step
from macromicro_sumo.policy.prior import RELAX_UPPER_S

# Candidates [s]: from near SUMO's Krauss (the step: a binds until the desired speed is
# within a x T) to the fit's bound (the neutral cruising the pairs fitted).
RELAX_CANDIDATES_S = (1.0, 2.0, 3.0, 5.0, 7.0, RELAX_UPPER_S)
# Scored over this span after the warm-up: the relaxation shapes how the population reaches
# its cruise (3 T: 30 s at the bound), and the first detector intervals hold it.
RELAX_SCORE_S = 120.0
# The fit's T counts as unidentified within this of its upper bound.
AT_BOUND_S = 0.01


def relax_unidentified(prior_params: Mapping[str, float]) -> bool:
    """True where the Krauss prior's relax_s [s] is at the fit's upper bound."""
    return float(prior_params["relax_s"]) >= RELAX_UPPER_S - AT_BOUND_S


class Loops:
    """SUMO's induction loops (``detectors.csv`` rows: lane_index, arc_m) read off the
    vehicles of a demand episode: a vehicle counts when its back leaves the loop, at its
    length over the time it occupied it, the crossings interpolated within the step.
    ``passages`` after each ``core.step``. Replaying ring_two_lane's truth (SUMO's models):
    the counts per minute are SUMO's within one; the speeds are within 0.01 m/s after the
    first minute, but 0.51 m/s fast in it (0.55 reading the speed as the front passes):
    SUMO's loops read the standing start in a way not reproduced here, two loops with a car
    inserted standing over them 1.3-1.6 m/s slower (hence ``choose_relax`` on counts)."""

    def __init__(self, loops: pd.DataFrame) -> None:
        self.arc_m = loops["arc_m"].to_numpy(dtype=float)
        self.lane = loops["lane_index"].to_numpy()
        self.arcs: dict[str, float] = {}  # vehicle -> its front's arc after the last step
        self.entered: dict[tuple[str, int], float] = {}  # (vehicle, loop) -> time on it [s]

    def passages(self, core: DemandCore) -> tuple[np.ndarray, np.ndarray]:
        """(loop index, speed [m/s]) of the vehicles that left a loop in the step just
        taken."""
        section, t1, dt = core.section, core.time_s(), core.dt
        ids, lanes, arcs, lengths = [], [], [], []
        for v, (lane_id, pos, _, _) in core.lane_states().items():
            hit = section.locate(lane_id, pos)
            if hit is not None and v in core.types:
                ids.append(v)
                lanes.append(hit[0])
                arcs.append(hit[1])
                lengths.append(core.vtypes[core.types[v]].length_m)
        if not ids:
            self.arcs = {}
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        arc, length = np.array(arcs), np.array(lengths)
        before = np.array([self.arcs.get(v, np.nan) for v in ids])
        self.arcs = dict(zip(ids, arcs, strict=True))
        same_lane = np.array(lanes)[:, None] == self.lane[None, :]

        def wrap(x: np.ndarray) -> np.ndarray:
            return np.mod(x, section.length_m) if section.closed else x

        moved = wrap(arc - before)  # NaN: new on the section
        new = np.isnan(before)
        # A vehicle first seen over a loop (a ring's fleet inserted standing) entered it then.
        over = same_lane & new[:, None] & (wrap(self.arc_m[None, :] - (arc - length)[:, None]) > 0)
        over &= wrap(self.arc_m[None, :] - (arc - length)[:, None]) <= length[:, None]
        for i, j in zip(*np.nonzero(over), strict=True):
            self.entered[(ids[i], int(j))] = t1
        out_loop, out_speed = [], []
        for offset, leaving in ((0.0, False), (length, True)):
            to_loop = wrap(self.arc_m[None, :] - (before - offset)[:, None])
            crossed = same_lane & (to_loop > 0.0) & (to_loop <= moved[:, None])
            for i, j in zip(*np.nonzero(crossed), strict=True):
                t = t1 - dt + dt * float(to_loop[i, j] / moved[i])
                if not leaving:
                    self.entered[(ids[i], int(j))] = t
                elif (t0 := self.entered.pop((ids[i], int(j)), None)) is not None:
                    out_loop.append(int(j))
                    out_speed.append(float(length[i]) / max(t - t0, 1e-6))
        return np.array(out_loop, dtype=np.int64), np.array(out_speed)


@dataclass(frozen=True)
class LoopFit:
    """The simulated loops against the truth's over a candidate's runs."""

    count_rmse: float  # vehicles per interval, all loops together
    speed_rmse_mps: float  # their mean speeds, where both saw a vehicle
    passages: int
    collisions: int
    teleports: int


def loop_fit(
    sc: Any,
    prior_params: Mapping[str, float],
    core: DemandCore,
    span_s: float,
    family: str | None = None,
) -> LoopFit:
    """``LoopFit`` over every run of ``core`` from SUMO's first step to ``span_s`` after the
    warm-up, the population driven by the prior of ``prior_params`` alone (``family``:
    its model, ``policy.prior``'s when None)."""
    agent = Agent(
        observation=sc.policy.observation,
        prior=family or sc.policy.prior,
        prior_params=prior_params,
    )
    dt, end_s = core.dt, sc.simulation.warmup_s + span_s
    det = core.truth.detectors
    counts, speeds, passages = [], [], 0
    c0, t0 = core.counts["collisions"], core.counts["teleports"]
    for run in core.runs:
        truth = det[(det["run"] == int(run)) & (det["end_s"] <= end_s + 1e-6)]
        loops = truth.drop_duplicates("detector_id").reset_index(drop=True)
        if loops.empty:
            continue
        edges = np.unique(np.concatenate([truth["begin_s"], truth["end_s"]]))
        total = np.zeros((len(loops), len(edges) - 1))
        count = np.zeros_like(total)
        core.reset(int(run), dt)
        reader = Loops(loops)
        for _ in range(int(round(end_s / dt)) - 1):
            prior_step(agent, core)
            loop, speed = reader.passages(core)
            k = np.searchsorted(edges, core.time_s(), side="left") - 1  # (begin, end]
            if 0 <= k < total.shape[1]:
                np.add.at(total[:, k], loop, speed)
                np.add.at(count[:, k], loop, 1.0)
        row = {d: i for i, d in enumerate(loops["detector_id"])}
        true_count = np.zeros_like(count)
        cols = ["detector_id", "begin_s", "n_veh", "speed_mps"]
        for d, b, n, v in truth[cols].itertuples(index=False):
            i, k = row[d], int(np.searchsorted(edges, b))
            true_count[i, k] = n
            if count[i, k] > 0 and n > 0:
                speeds.append(total[i, k] / count[i, k] - v)
        # Summed over the loops: which lane a vehicle passes on is SUMO's lane choice, noise
        # here (per loop, the candidates' count RMSEs did not order by T).
        counts.extend(count.sum(axis=0) - true_count.sum(axis=0))
        passages += int(count.sum())

    def rms(x: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")

    return LoopFit(
        rms(counts),
        rms(speeds),
        passages,
        core.counts["collisions"] - c0,
        core.counts["teleports"] - t0,
    )


def choose_relax(
    sc: Any,
    prior_params: Mapping[str, float],
    make_demand: Callable[[], DemandCore],
    candidates: tuple[float, ...] = RELAX_CANDIDATES_S,
    span_s: float = RELAX_SCORE_S,
) -> tuple[float, dict[str, Any]]:
    """(relax_s [s], what the manifest records): the candidate (at least the step) whose
    loops' counts are closest to the truth's (``LoopFit.count_rmse``), among those without
    a collision where any has none; equal ones keep the larger T (the fit's side). Counts,
    not speeds: SUMO's loops read the standing start's speeds in a way the emulation does
    not (replayed with SUMO's own models, ring_two_lane's first minute 0.51 m/s fast, the
    later ones within 0.01), while its counts agree (154 / 164 / 162 / 166 against
    154 / 164 / 163 / 166 per minute), and a slower start passes fewer vehicles."""
    dt = sc.simulation.step_length_s
    core = make_demand()
    rows: list[tuple[float, LoopFit]] = []
    try:
        for t in sorted({max(float(c), dt) for c in candidates}, reverse=True):
            fit = loop_fit(sc, {**prior_params, "relax_s": t}, core, span_s, family="krauss")
            rows.append((t, fit))
        runs = [int(r) for r in core.runs]
    finally:
        core.close()
    safe = [r for r in rows if r[1].collisions == 0 and np.isfinite(r[1].count_rmse)] or rows
    best = min(safe, key=lambda r: r[1].count_rmse)  # the first of equals: the larger T
    record = {
        "fitted_s": float(prior_params["relax_s"]),
        "chosen_s": best[0],
        "runs": runs,
        "span_s": span_s,
        "candidates": {f"{t:g}": asdict(f) for t, f in rows},
    }
    return best[0], record
