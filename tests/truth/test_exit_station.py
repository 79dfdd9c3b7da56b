"""A station near an open section's end counts, in its interval counts, every vehicle that
passes it, also those whose route ends at the section's end (SUMO's E1 loop does not count
a vehicle that arrives with its back still on it: ``section_detectors.exit_arc``)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from conftest import dump_toml, netconvert

from macromicro_sumo.cli import main


def test_interval_counts_equal_passages_at_the_exit(tmp_path: Path) -> None:
    # One 453 m lane ending in a dead end: with a loop every 100 m the grid's last loop
    # would sit at 450 m, 3 m before the end where every 5 m car arrives.
    net = netconvert(
        tmp_path,
        '<node id="a" x="0" y="0"/><node id="b" x="453" y="0"/>',
        '<edge id="e" from="a" to="b" numLanes="1" speed="10" priority="1"/>',
        name="x",
    )
    (tmp_path / "x.rou.xml").write_text(
        '<routes><vType id="car" length="5" minGap="2.5"/><route id="r" edges="e"/>'
        '<flow id="f" type="car" route="r" begin="0" end="240" vehsPerHour="900" '
        'departSpeed="max"/></routes>'
    )
    table = {
        "name": "exit",
        "seed": 3,
        "network": {
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(tmp_path / "x.rou.xml")],
        },
        "section": {"edges": ["e"], "closed": False},
        "instrumented": {"penetration": 0.1},
        "simulation": {"warmup_s": 30.0, "duration_s": 330.0, "n_runs": 1},
        "detectors": {"interval_s": 30.0, "auto_spacing_m": 100.0, "k_window_s": 30.0},
        "generator": {"snapshot_every_s": 5.0},
    }
    toml = tmp_path / "exit.toml"
    toml.write_text(dump_toml(table))
    gt = tmp_path / "gt"
    assert main(["simulate", str(toml), "--out", str(gt), "--quiet"]) == 0
    det = pd.read_csv(gt / "detectors.csv")
    pas = pd.read_csv(gt / "detector_passages.csv", dtype={"vehicle_id": str})
    counts = det.groupby("arc_m")["n_veh"].sum()
    arcs = det.groupby("detector_id")["arc_m"].first()
    seen = pas.assign(arc_m=pas["detector_id"].str.removeprefix("i_").map(arcs))
    passed = seen.groupby("arc_m")["vehicle_id"].nunique()
    assert passed.min() > 50  # the flow (about 60 cars) crossed every station
    pd.testing.assert_series_equal(counts, passed, check_names=False, check_dtype=False)
    assert counts.index.max() <= 453.0 - 15.0 + 0.5  # no loop in the arrival zone
