"""``policy.driver_entry = "auto"`` on a signalised road (``env.driver_speed.entry_choice``):
the observed drivers first seen standing in a red light's queue are held, below their
speed, but "queued" draws them as well, so they do not choose between the rules; read with
them (stop 44) the rule chose "held" on the drawn arterials and lost there (528: 1.370 ->
1.465 m/s). Real SUMO: a light 120 m past the entry whose red queue reaches back past it
(stop 45)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import dump_toml, light_road

from macromicro_sumo.env.driver_speed import (
    ENTRY_AT_OWN_SHARE,
    MIN_HELD_SIGHTS,
    QUEUED_ENTRY_SHARE,
    entry_choice,
    first_sights,
    held_at_sight,
)
from macromicro_sumo.env.driver_speed_ratios import QUANTILE_LEVELS, ratio_estimate
from macromicro_sumo.env.observed_drivers import observed_drivers, ratio_censoring
from macromicro_sumo.road.physics import LIMIT_COLUMN
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth, simulate_section

LIMIT_MPS = 15.0


def red_queue_scenario(folder: Path) -> Path:
    """One lane A (120 m) -> a light (green 20 s, yellow 3 s, red 37 s) -> B (400 m) at 15
    m/s, a car every 2 s inserted at departSpeed "max" (behind the red's queue: the safe
    speed there, standing); every vehicle instrumented."""
    net = light_road(folder, 120.0, 400.0, LIMIT_MPS)
    routes = folder / "r.rou.xml"
    routes.write_text(
        "<routes>\n"
        '    <vType id="car" length="5" minGap="2.5" speedFactor="1.0" speedDev="0.05"/>\n'
        '    <route id="r" edges="A B"/>\n'
        '    <flow id="c" type="car" route="r" begin="0" end="3600" period="2" '
        'departSpeed="max"/>\n'
        "</routes>\n"
    )
    program = folder / "tl.add.xml"
    program.write_text(
        '<additional>\n    <tlLogic id="tl" type="static" programID="cycle" offset="0">\n'
        '        <phase duration="20" state="G"/>\n        <phase duration="3" state="y"/>\n'
        '        <phase duration="37" state="r"/>\n    </tlLogic>\n</additional>\n'
    )
    table = {
        "name": "red_queue",
        "seed": 5,
        "network": {
            "kind": "sumo",
            "net_file": str(net),
            "route_files": [str(routes)],
            "additional_files": [str(program)],
        },
        "section": {"edges": ["A", "B"]},
        "instrumented": {"penetration": 1.0},
        "simulation": {"warmup_s": 120.0, "duration_s": 480.0, "n_runs": 1},
        "detectors": {"interval_s": 60.0, "auto_spacing_m": 200.0},
        "policy": {"prior": "gipps", "driver_speed": "memory"},
    }
    path = folder / "red_queue.toml"
    path.write_text(dump_toml(table))
    return path


def test_first_sights_standing_in_a_reds_queue_do_not_choose_held(tmp_path: Path) -> None:
    sc = load_scenario(red_queue_scenario(tmp_path))
    truth = load_section_truth(simulate_section(sc, tmp_path / "gt", progress=False), sc)
    drivers = observed_drivers(sc, truth, truth.runs)
    idx = first_sights(drivers)
    obs = drivers.obs[idx]
    held = held_at_sight(obs, gap_layout=False)
    keys = [drivers.keys[i] for i in idx.tolist()]
    top = np.array([drivers.ratio.get(k, drivers.lower.get(k, np.nan)) for k in keys])
    ratio = obs[:, 0] / obs[:, LIMIT_COLUMN]
    read = held & np.isfinite(top)
    # Stop 44's reading, every held first sight: many, standing or crawling in the queue
    # far below their tops, so "held" (measured: 110 of 111, at a median 0.18)
    assert read.sum() >= 10 * MIN_HELD_SIGHTS
    assert np.median(ratio[read] / top[read]) < 0.3 < ENTRY_AT_OWN_SHARE
    # "queued" draws them too: below QUEUED_ENTRY_SHARE of the observed median (all 110)
    quantiles = ratio_estimate(drivers, ratio_censoring(sc)).quantiles
    median = np.interp(0.5, QUANTILE_LEVELS, quantiles)
    assert np.mean(ratio[read] / median < QUEUED_ENTRY_SHARE) > 0.9
    # so the rule has too few others to read, and stays at the default's "queued"
    choice = entry_choice(drivers, gap_layout=False, censoring=ratio_censoring(sc))
    assert choice.held_sights < MIN_HELD_SIGHTS
    assert choice.entry == "queued"
