"""``bounds.psi_min_gap``: psi's smallest spacing is the shortest recorded vType plus
``bounds.min_gap_m`` (the default), or plus the recorded vTypes' smallest minGap
("recorded"), where the truth records one; on a real ring-as-section truth (SUMO)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import ROOT

from macromicro_sumo.data.section import psi_min_gap_m, psi_table
from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth

NETGEN = ROOT / "scenarios" / "netgen_corridor.toml"


def _with(sc, value: str):
    return dataclasses.replace(sc, bounds=dataclasses.replace(sc.bounds, psi_min_gap=value))


def test_psi_min_gap_recorded_takes_the_vtypes_smallest_min_gap(ring_section_truth) -> None:
    sc, gt = ring_section_truth
    truth = load_section_truth(gt, sc)
    assert sc.bounds.psi_min_gap == "bounds" and "psi_min_gap" not in sc.to_dict()["bounds"]
    shortest = float(truth.vtypes["length_m"].min())
    vt = truth.vtypes.copy()
    vt["min_gap_m"] = np.linspace(3.5, 2.75, len(vt))  # smallest 2.75 m (one vType: 3.5)
    wider = dataclasses.replace(truth, vtypes=vt)
    base = psi_table(wider, sc)["spacing_min_m"]
    assert np.allclose(base, shortest + sc.bounds.min_gap_m)
    rec = psi_table(wider, _with(sc, "recorded"))
    assert psi_min_gap_m(wider, _with(sc, "recorded")) == float(vt["min_gap_m"].min())
    assert np.allclose(rec["spacing_min_m"], shortest + float(vt["min_gap_m"].min()))
    assert (rec["spacing_low_m"] == rec["spacing_min_m"]).all()  # no spacing_bounds here
    # A truth without minGaps (an older ground truth): bounds.min_gap_m as before.
    bare = dataclasses.replace(truth, vtypes=truth.vtypes.drop(columns="min_gap_m"))
    assert psi_min_gap_m(bare, _with(sc, "recorded")) == sc.bounds.min_gap_m


def test_a_bad_psi_min_gap_is_refused() -> None:
    with pytest.raises(UserError, match="bounds.psi_min_gap") as err:
        load_scenario(NETGEN, {"bounds.psi_min_gap": "vtypes"})
    assert "\n" not in str(err.value) and "'recorded'" in str(err.value)
    assert (
        load_scenario(NETGEN, {"bounds.psi_min_gap": "recorded"}).to_dict()["bounds"]["psi_min_gap"]
        == "recorded"
    )
