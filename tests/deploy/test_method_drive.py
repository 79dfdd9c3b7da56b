"""``deploy.stage.method_drive`` for the two calibrated IDMs: each drives its own fit, and
refuses without it (a ``Drive`` without theta drives the truth's own vTypes: the oracle
under another name, which scripts/deploy_runs.py once reported as idm_detectors)."""

from __future__ import annotations

import pytest

from macromicro_sumo.deploy.stage import method_drive
from macromicro_sumo.evaluation.idm_fit import IdmParams


def test_idm_detectors_drives_its_fit_and_refuses_without_it() -> None:
    fitted = {"accel": 1.7, "decel": 3.1, "tau": 1.2, "minGap": 2.4}
    drive, record = method_drive("idm_detectors", None, {}, None, fitted)
    assert drive.theta == fitted and record["theta"] == fitted
    with pytest.raises(ValueError, match="idm_detectors: needs the IDM fitted to the detectors"):
        method_drive("idm_detectors", None, {}, None, None)


def test_idm_calibrated_refuses_without_the_observed_fit() -> None:
    with pytest.raises(ValueError, match="idm_calibrated: needs the IDM fitted"):
        method_drive("idm_calibrated", None, {}, None)
    idm = IdmParams(speed_factor=1.05, tau_s=1.3, accel_mps2=1.6, decel_mps2=2.9, min_gap_m=2.2)
    drive, _ = method_drive("idm_calibrated", None, {}, idm)
    assert drive.theta is not None and drive.theta["accel"] == pytest.approx(idm.accel_mps2)
