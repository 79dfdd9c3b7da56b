"""How many of SUMO's leaders (``Simulation.leaders``, getLeader per driven vehicle) a
Bremen policy run could read from the step's state instead, to the bit: the next vehicle
ahead on the same lane in ``Simulation.vehicle_states`` (SUMO's MSVehicle::getLeader takes
the next vehicle of the lane's own list, gap = its back - own position - own minGap,
whatever the look-ahead), and what each way costs.

Per answer of getLeader, one of: the same-lane next vehicle with the same gap to the bit
(``same_lane_bit_equal``) or another gap (``same_lane_not_equal``); another vehicle though
one is ahead on the lane (``other_leader``); a leader while none is ahead on the lane
(``first_on_lane``: SUMO looks on along its best lanes); none (``none``). Then thread CPU
per step of the getLeader calls and of ``same_lane_leaders`` (numpy, every vehicle sorted
by lane and position) on the same states. A lever for ``scripts/bench_deploy.py``'s ratio
only where the bit-equal share is large and the numpy cost below the calls it saves.

    PYTHONPATH=$PWD .venv/bin/python scripts/bench_leaders.py [--checkpoint POLICY.pt]
"""

from __future__ import annotations

import argparse
import importlib.util
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from macromicro_sumo.sumo.simulation import Simulation
from macromicro_sumo.sumo.states import VehicleStates

HERE = Path(__file__).resolve().parent


def same_lane_leaders(
    st: VehicleStates, rows: np.ndarray, length_m: np.ndarray, min_gap_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per vehicle at rows ``rows`` of ``st``, the row of the next vehicle ahead on its lane
    (-1: none, or one at the same position: SUMO's order between them unknown) and
    (its position - its length) - own position - own minGap (NaN where -1); ``length_m``,
    ``min_gap_m``: per row of ``st``."""
    code: dict[str, int] = {}
    lane = np.fromiter(map(code.setdefault, st.lanes, range(len(st.lanes))), np.int64)
    order = np.lexsort((st.pos_m, lane))
    nxt = np.full(len(lane), -1, dtype=np.int64)
    nxt[order[:-1]] = order[1:]
    lead = nxt[rows]
    ok = (lead >= 0) & (lane[lead] == lane[rows]) & (st.pos_m[lead] > st.pos_m[rows])
    lead = np.where(ok, lead, -1)
    gap = (st.pos_m[lead] - length_m[lead]) - st.pos_m[rows] - min_gap_m[rows]
    return lead, np.where(ok, gap, np.nan)


def classify(
    st: VehicleStates,
    vids: list[str],
    leaders: list[tuple[str, float]],
    shape: dict[str, tuple[float, float]],
) -> Counter:
    """The kinds (module doc) of getLeader's answers ``leaders`` for vehicles ``vids`` on
    the road in ``st``; ``shape``: vehicle -> (length, minGap), its vType's."""
    rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, len(vids))
    length = np.array([shape[v][0] for v in st.ids])
    min_gap = np.array([shape[v][1] for v in st.ids])
    lead, gap = same_lane_leaders(st, rows, length, min_gap)
    out: Counter = Counter()
    for i, (lid, g) in enumerate(leaders):
        j = int(lead[i])
        if not lid:
            out["none"] += 1
        elif j < 0:
            out["first_on_lane"] += 1
        elif st.ids[j] != lid:
            out["other_leader"] += 1
        else:
            out["same_lane_bit_equal" if gap[i] == g else "same_lane_not_equal"] += 1
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=Path("runs/highway_bremen/policy/policy.pt"),
        help="the Bremen policy (else bench_deploy's untrained one)",
    )
    args = ap.parse_args(argv)
    spec = importlib.util.spec_from_file_location("bench_deploy", HERE / "bench_deploy.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    from macromicro_sumo.deploy.policy_batch import policy_batch

    torch.set_num_threads(1)
    kinds: Counter = Counter()
    cpu = {"getLeader": 0.0, "same_lane_leaders": 0.0, "steps": 0}
    shape: dict[str, tuple[float, float]] = {}
    plain = Simulation.leaders

    def leaders(self: Simulation, vids, lookahead_m):  # type: ignore[no-untyped-def]
        t0 = time.thread_time()
        out = plain(self, vids, lookahead_m)
        cpu["getLeader"] += time.thread_time() - t0
        st = self.vehicle_states()
        for v in st.ids:
            if v not in shape:
                shape[v] = self.vtype_shape(self.vehicle_type(v))[:2]
        rows = np.fromiter(map(st.index.__getitem__, vids), np.int64, len(vids))
        length = np.array([shape[v][0] for v in st.ids])
        min_gap = np.array([shape[v][1] for v in st.ids])
        t0 = time.thread_time()
        same_lane_leaders(st, rows, length, min_gap)
        cpu["same_lane_leaders"] += time.thread_time() - t0
        cpu["steps"] += 1
        kinds.update(classify(st, list(vids), out, shape))
        return out

    Simulation.leaders = leaders  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as t:
            tmp = Path(t)
            sc = bench.bremen_scenario(tmp)
            agent, which = bench.agent_for(sc, args.checkpoint)
            bench.bremen_run(sc, tmp, "policy", policy_batch(agent, sc.deploy.actor_dtype))
    finally:
        Simulation.leaders = plain  # type: ignore[method-assign]
    n, steps = sum(kinds.values()), max(cpu["steps"], 1)
    print(f"policy: {which}; {n:,} getLeader answers in {steps:,} steps")
    for k, v in kinds.most_common():
        print(f"  {k:22s} {v:8,d}  {v / max(n, 1):6.1%}")
    print(
        f"thread CPU a step: getLeader {1e6 * cpu['getLeader'] / steps:.1f} us "
        f"({1e6 * cpu['getLeader'] / max(n, 1):.2f} a call), same_lane_leaders "
        f"{1e6 * cpu['same_lane_leaders'] / steps:.1f} us (every vehicle)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
