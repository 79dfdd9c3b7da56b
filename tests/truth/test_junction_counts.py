"""The junction stretches of a signalised section counted from their stop bars' interval
counts timed by the programs (``truth.junction_counts``, a diagnostic), in real SUMO, against
the vehicles the simulation had there."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_hidden_count_queues import arterial_scenario

from macromicro_sumo.cli import main
from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.truth.interval_counts import interval_record
from macromicro_sumo.truth.junction_counts import junction_pieces, junction_stretches
from macromicro_sumo.truth.signal_counts import approach_pieces
from macromicro_sumo.truth.signal_lines import stop_lines


@pytest.fixture(scope="module")
def arterial(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("junctions")
    gt = folder / "gt"
    assert main(["simulate", str(arterial_scenario(folder)), "--out", str(gt), "--quiet"]) == 0
    return gt, folder / "art.net.xml"


def test_junction_stretches_follow_the_cycle(arterial: tuple[Path, Path]) -> None:
    """Three junctions: each stretch runs from its stop bar to the station past the
    junction; counted from the stop bar's passing seconds its vehicles are nearer the truth
    than the interval density estimate over it (which holds a cycle's mean at every
    snapshot; 1.45 vehicles off over the three against 3.79 measured), and the count swings
    with the cycle as the truth does (correlation 0.85; the truth 0-12 vehicles)."""
    gt, net_file = arterial
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv")
    record = interval_record(det, section, read_net(net_file), net_file)
    assert record is not None
    lines = stop_lines(net_file, section)
    stretches = junction_stretches(record.det, section, lines)
    assert len(stretches) == 3
    for j, line in zip(stretches, lines, strict=True):
        assert j.up_m <= line.arc_m < j.bar_m
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    snaps = at_snapshot_times(traj, 5.0)
    times = np.sort(snaps["time_s"].unique())
    times = times[times >= 90.0]  # past the first interval: the section has filled
    by_t = snaps.groupby("time_s")["arc_m"]
    pieces, rest = approach_pieces(record.det, section, lines, record.side_arcs, 0, times)
    more, less = junction_pieces(record.det, section, lines, 0, times, rest)
    (piece,) = more.values()
    true = np.array(
        [
            sum(((a >= lo) & (a < hi)).sum() for lo, hi in piece.arcs_m)
            for a in (by_t.get_group(t).to_numpy() for t in times)
        ]
    )
    # The density estimate the rest held over the junctions, at each snapshot's interval.
    dens = (rest["vehicles"] - less["vehicles"]).to_numpy()
    k = np.clip(np.searchsorted(rest["begin_s"].to_numpy(), times, side="right") - 1, 0, None)
    counted_err = float(np.abs(piece.vehicles - true).mean())
    density_err = float(np.abs(dens[k] - true).mean())
    assert true.max() - true.min() >= 6  # the junctions fill at green and empty at red
    assert counted_err < 0.8 * density_err, (counted_err, density_err)
    assert np.corrcoef(piece.vehicles, true)[0, 1] >= 0.5


def test_the_rest_loses_the_junctions_density(arterial: tuple[Path, Path]) -> None:
    """``junction_pieces`` leaves the rest with less in every interval, by the density
    estimate over the junction stretches (what K holds on them: not the count, as the
    approach past a junction already counts its vehicles from the stop bar on), positive
    and below what the stretches hold at jam spacing."""
    gt, net_file = arterial
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv")
    record = interval_record(det, section, read_net(net_file), net_file)
    assert record is not None
    times = np.arange(100.0, 480.0, 10.0)
    lines = list(record.stop_lines)
    _, rest = approach_pieces(record.det, section, lines, record.side_arcs, 0, times)
    more, less = junction_pieces(record.det, section, lines, 0, times, rest)
    assert less[["begin_s", "end_s"]].equals(rest[["begin_s", "end_s"]])
    held = (rest["vehicles"] - less["vehicles"]).to_numpy()
    room = sum(hi - lo for lo, hi in more["junctions"].arcs_m) * 2 / 7.5  # 2 lanes, jammed
    assert (held > 0).all() and (held < room).all(), held
