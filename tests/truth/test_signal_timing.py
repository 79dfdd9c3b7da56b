"""Front-loaded departures at a stop line (``truth.signal_timing``, opt-in): the red's queue
leaves first at the saturation flow, then the arrivals at their own flow."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from test_hidden_count_queues import signal_scenario
from test_signal_counts import simulated

from macromicro_sumo.data.section import at_snapshot_times
from macromicro_sumo.road.section import Section
from macromicro_sumo.sumo.inputs import read_net
from macromicro_sumo.truth import signal_timing
from macromicro_sumo.truth.interval_counts import interval_record
from macromicro_sumo.truth.signal_counts import approach_pieces
from macromicro_sumo.truth.signal_lines import StopLine, stop_lines

# netconvert's 90 s program: the section's lanes pass from 45 s to 90 s of each cycle.
LINE = StopLine(100.0, 0.0, (42.0, 3.0, 42.0, 3.0), (False, False, True, True))


def test_the_reds_queue_leaves_first_at_the_saturation_flow() -> None:
    """18 vehicles in a 90 s interval on one lane (0.2 veh/s): the red's (45 s) queue of 9
    leaves at one per 2 s from 45 s on, so it is gone 12.86 s into the green (9 / (0.5 -
    0.2) x 0.5 ... the queue plus the arrivals behind it), then 0.2 veh/s; none in the red."""
    t = np.array([0.0, 44.0, 45.0, 50.0, 57.86, 90.0])
    f = signal_timing.front_fraction(LINE, 0.0, 90.0, 0.2, 1, t)
    assert f is not None
    n = 18.0 * f
    assert n[0] == pytest.approx(0.0) and n[1] == pytest.approx(0.0)
    assert n[3] - n[2] == pytest.approx(2.5, abs=0.05)  # 0.5 veh/s at saturation, 5 s
    assert n[-1] == pytest.approx(18.0)
    even = 18.0 * 5.0 / 45.0  # spread over the green: 2.0 in its first 5 s
    assert n[3] - n[2] > even
    # The queue (45 s x 0.2 = 9 plus the arrivals while it leaves) is out by ~57.9 s: the
    # rest of the green passes its arrivals at their flow, slower than saturation.
    rate_late = (n[5] - n[4]) / (90.0 - 57.86)
    assert rate_late < 0.5


def test_a_crossing_later_and_no_green() -> None:
    """A station 30 m past the line at 10 m/s sees the same departures 3 s later (the same
    shape; its interval's share renormalised, the last 3 s of green falling past it); an
    interval in which the line never lets pass has none to front-load (None)."""
    t = np.array([46.0, 50.0, 60.0])
    at_bar = signal_timing.front_fraction(LINE, 0.0, 90.0, 0.2, 1, t)
    later = signal_timing.front_fraction(LINE, 0.0, 90.0, 0.2, 1, t + 3.0, delay_s=3.0)
    assert at_bar is not None and later is not None
    assert np.diff(later) / np.diff(later).sum() == pytest.approx(
        np.diff(at_bar) / np.diff(at_bar).sum(), abs=1e-6
    )
    assert later[0] > at_bar[0] - 1e-9  # the previous green's tail reaches it in 0-3 s
    red_only = StopLine(100.0, 0.0, (40.0, 50.0), (False, True))
    assert signal_timing.front_fraction(red_only, 0.0, 40.0, 0.1, 1, np.array([20.0])) is None


def test_front_loaded_departures_follow_the_green_in_sumo(tmp_path, monkeypatch) -> None:
    """One fixed-time junction in real SUMO (``test_signal_counts``' scene, 30 s intervals):
    the approach's count just after the start of green. Front-loaded, the stop bar's count
    takes the red's queue out first, as SUMO's queue leaves; spread evenly over the green
    it leaves too slowly and the count stays high. Measured: the mean error over the
    snapshots within 15 s after each start of green, even / front."""
    gt, net_file = simulated(tmp_path, signal_scenario, "x.net.xml")
    section = Section.read(gt / "section.json")
    det = pd.read_csv(gt / "detectors.csv")
    lines = stop_lines(net_file, section)
    record = interval_record(det, section, read_net(net_file), net_file)
    assert record is not None
    traj = pd.read_csv(gt / "trajectories.csv", dtype={"vehicle_id": str, "vtype": str})
    snaps = at_snapshot_times(traj, 1.0)
    times = np.sort(snaps["time_s"].unique())
    starts = np.array([t for t, _ in lines[0].green_starts(times[0], times[-1])])
    since = times - starts[np.clip(np.searchsorted(starts, times, "right") - 1, 0, None)]
    early = times[(since >= 3.0) & (since <= 15.0) & (times >= starts[0])]
    by_t = snaps.groupby("time_s")["arc_m"]
    bias = {}
    for timing in ("even", "front"):
        monkeypatch.setattr(signal_timing, "TIMING", timing)
        pieces, _ = approach_pieces(record.det, section, lines, record.side_arcs, 0, early)
        ((lo, hi),) = pieces["approaches"].arcs_m
        true = np.array([((a >= lo) & (a < hi)).sum() for a in (by_t.get_group(t) for t in early)])
        bias[timing] = float(np.mean(pieces["approaches"].vehicles - true))
    print(bias)
    assert bias["front"] < bias["even"]
