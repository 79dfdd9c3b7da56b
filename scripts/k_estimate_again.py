"""The hidden count K of a finished ground truth estimated again by this checkout, as
``macromicro simulate`` writes ``k_estimate.csv`` (``truth.section``: the stations' record
with the network's side junctions, the passage lag, the empty start where no fleet runs),
without simulating: a change to ``truth/`` measured before -> after on a run's ground truth
(run it once with each checkout on PYTHONPATH). Prints per ground truth K's mean absolute
error per lane, its bias (vehicles), per lane free / congested (a snapshot is congested when
10% of its vehicles are at or below 5 m/s, as ``bench_hidden_count.py`` counts), and the md5
of the estimate against that of the ``k_estimate.csv`` on disk (equal: unchanged).

    PYTHONPATH=. .venv/bin/python scripts/k_estimate_again.py SCENARIO.toml RUN/ground_truth \\
        [SCENARIO.toml GT ...]
"""

from __future__ import annotations

import hashlib
import io
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fleet import fleet_demand
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import read_net, scenario_inputs
from macromicro_sumo.truth.hidden_count import k_estimates
from macromicro_sumo.truth.section import load_section_truth
from macromicro_sumo.truth.section_macro import k_summary
from macromicro_sumo.truth.stations import PASSAGE_LAG_STEPS, StationRecord, side_junction_arcs

SLOW_MPS, SLOW_SHARE = 5.0, 0.1  # bench_hidden_count.py's congested snapshot


def again(toml: Path, gt: Path) -> tuple[pd.DataFrame, str, str]:
    """(K per snapshot with a ``congested`` column, md5 of the estimate as simulate writes
    it, md5 of the ``k_estimate.csv`` in ``gt``)."""
    sc = load_scenario(toml)
    truth = load_section_truth(gt)
    passages = gt / "detector_passages.csv"
    if not passages.is_file():
        raise UserError(f"{passages}: missing (a ground truth of a section with E1 stations)")
    pas = pd.read_csv(passages, dtype={"vehicle_id": str})
    record = StationRecord(
        truth.detectors,
        pas,
        side_junction_arcs(read_net(scenario_inputs(sc).net_file), truth.section),
        PASSAGE_LAG_STEPS * sc.simulation.step_length_s,
        from_empty=fleet_demand(sc) is None,
    )
    k = k_estimates(
        truth.trajectories,
        truth.macro[truth.macro["source"] == "detectors"],
        truth.section,
        sc.generator.snapshot_every_s,
        sc.detectors.k_window_s,
        record,
    )
    buf = io.StringIO()  # files.write_csv's format
    k.to_csv(buf, index=False, float_format="%.6f", lineterminator="\n")
    md5 = hashlib.md5(buf.getvalue().encode()).hexdigest()
    own = hashlib.md5((gt / "k_estimate.csv").read_bytes()).hexdigest()
    snaps = at_snapshot_times(truth.trajectories, sc.generator.snapshot_every_s)
    slow = snaps.groupby(["run", "time_s"])["speed_mps"].apply(
        lambda v: (v <= SLOW_MPS).mean() >= SLOW_SHARE
    )
    k = k.merge(slow.rename("congested").reset_index(), on=["run", "time_s"], how="left")
    return k, md5, own


def line(toml: Path, gt: Path) -> str:
    """One ground truth's row: K per lane, bias, free / congested per lane, md5s."""
    k, md5, own = again(toml, gt)
    truth = load_section_truth(gt)
    s = truth.section
    lanes = float((s.n_lanes * s.lengths_m).sum() / s.lengths_m.sum())
    summary = k_summary(k, s)
    parts = [
        f"{'congested' if c else 'free'} {np.abs(g['k_error']).mean() / lanes:.2f} ({len(g)})"
        for c, g in k.groupby("congested")
    ]
    same = "unchanged" if md5 == own else "changed"
    return (
        f"{gt}: K/lane {summary['mean_abs_error_per_lane_veh']:.2f} bias "
        f"{summary['mean_error_veh']:+.2f} | {' | '.join(parts)} | md5 {md5[:10]} ({same})"
    )


def main(args: list[str]) -> int:
    if not args or len(args) % 2:
        print(__doc__, file=sys.stderr)
        return 2
    for toml, gt in zip(args[::2], args[1::2], strict=True):
        print(line(Path(toml), Path(gt)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
