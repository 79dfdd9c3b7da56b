"""The detector calibration's search and objective, on functions and frames with known answers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.deploy.calibrate import IDM_RANGES, calibrate, detector_loss


def test_the_search_finds_a_known_minimum_inside_the_box() -> None:
    target = {"accel": 1.2, "decel": 2.0, "tau": 1.4, "minGap": 2.5, "speedFactor": 1.05}

    def loss(p: dict[str, float]) -> float:
        return sum(
            ((p[k] - v) / (IDM_RANGES[k][1] - IDM_RANGES[k][0])) ** 2 for k, v in target.items()
        )

    cal = calibrate(loss, budget_s=30.0, max_evals=400)
    for k, v in target.items():
        assert cal.params[k] == pytest.approx(v, abs=0.05 * (IDM_RANGES[k][1] - IDM_RANGES[k][0]))
    assert cal.loss == cal.history["loss"].min()
    assert list(cal.history["eval"]) == list(range(len(cal.history)))


def test_the_search_stops_at_its_evaluation_budget_and_keeps_the_best() -> None:
    cal = calibrate(lambda p: (p["tau"] - 2.0) ** 2, {"tau": (0.5, 2.5)}, max_evals=7)
    assert len(cal.history) == 7 and cal.stopped_by == "evaluations"
    assert cal.loss == pytest.approx(cal.history["loss"].min())


def test_detector_loss_is_zero_for_the_truth_and_grows_with_the_error() -> None:
    truth = pd.DataFrame(
        {
            "run": 0,
            "detector_id": ["a", "a", "b"],
            "begin_s": [0.0, 60.0, 0.0],
            "flow_vph": [1000.0, 1200.0, 0.0],
            "speed_mps": [20.0, 10.0, np.nan],
        }
    )
    assert detector_loss(truth, truth) == 0.0
    off = truth.assign(speed_mps=truth["speed_mps"] * 1.1)
    assert detector_loss(truth, off) == pytest.approx(0.1)
    # A lost detector counts as zero flow: GEH sqrt(2 * 1000^2 / 1000) = 44.7 and 49.0
    lost = truth[truth["begin_s"] > 0]
    expect = (np.sqrt(2000.0) + 0.0 + 0.0) / 3 / 5.0
    assert detector_loss(truth, lost) == pytest.approx(expect, rel=1e-6)
