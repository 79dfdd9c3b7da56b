"""scripts/deploy_intervals.py: pooling a deployment's comparison into longer intervals."""

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.deploy.compare import ALL_LANES, detector_scores, geh, relative_error

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "deploy_intervals.py"


@pytest.fixture(scope="module")
def pooled():
    spec = importlib.util.spec_from_file_location("deploy_intervals", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.pooled


def comparison(seed: int = 0, n: int = 12) -> pd.DataFrame:
    """Two stations over n 30 s intervals with drawn flows and speeds, and a lane row."""
    rng = np.random.default_rng(seed)
    rows = []
    for station, arc in (("e1_100m", 100.0), ("e1_900m", 900.0)):
        for i in range(n):
            qt, qm = rng.integers(0, 40, 2) * 120.0
            vt, vm = rng.uniform(20, 40, 2)
            rows.append(
                {
                    "method": "policy", "run": 1, "station": station, "lane": ALL_LANES,
                    "begin_s": 30.0 * i, "end_s": 30.0 * (i + 1), "arc_m": arc,
                    "flow_truth_vph": qt, "flow_method_vph": qm,
                    "speed_truth_mps": vt if qt > 0 else np.nan,
                    "speed_method_mps": vm if qm > 0 else np.nan,
                    "density_truth_vpkm": qt / vt / 3.6, "density_method_vpkm": qm / vm / 3.6,
                }
            )  # fmt: skip
    c = pd.DataFrame(rows)
    c["geh"] = geh(c["flow_method_vph"], c["flow_truth_vph"])
    c["speed_rel_error"] = relative_error(c["speed_method_mps"], c["speed_truth_mps"])
    lane = c.assign(lane=0)  # per-lane rows are not station-intervals: left out
    return pd.concat([c, lane], ignore_index=True)


def test_one_interval_blocks_give_the_summary(pooled):
    c = comparison()
    a, b = detector_scores(c), detector_scores(pooled(c, 1))
    for k in ("station_intervals", "share_geh_below_5", "share_speed_within_5pct"):
        assert a[k] == pytest.approx(b[k])
    assert a["speed_rmse_mps"] == pytest.approx(b["speed_rmse_mps"])


def test_blocks_pool_counts_and_space_mean_speeds(pooled):
    c = comparison(seed=3, n=5)
    p = pooled(c, 2)
    # 5 intervals make two whole blocks of 2 per station; the fifth is left out
    assert len(p) == 4
    assert set(p["end_s"] - p["begin_s"]) == {60.0}
    s = c[(c["lane"] == ALL_LANES) & (c["station"] == "e1_900m") & (c["begin_s"] < 60)]
    first = p[(p["station"] == "e1_900m") & (p["begin_s"] == 0.0)].iloc[0]
    q, v = s["flow_truth_vph"].to_numpy(), s["speed_truth_mps"].to_numpy()
    assert first["flow_truth_vph"] == pytest.approx(q.mean())
    ok = q > 0
    if ok.any():  # the harmonic mean of the vehicles that passed, weighted by their counts
        assert first["speed_truth_mps"] == pytest.approx(q[ok].sum() / (q[ok] / v[ok]).sum())
    assert first["geh"] == pytest.approx(
        geh(np.array([first["flow_method_vph"]]), np.array([first["flow_truth_vph"]]))[0]
    )


def test_longer_intervals_loosen_geh_on_timing_noise(pooled):
    """The same mean flow with each 30 s count three vehicles off, alternately: GEH fails at
    30 s and holds once pairs of intervals are pooled."""
    c = comparison(n=8)
    c = c[c["lane"] == ALL_LANES].copy()
    c["flow_truth_vph"] = 480.0
    c["flow_method_vph"] = np.where((c["begin_s"] // 30) % 2 == 0, 480.0 + 360.0, 480.0 - 360.0)
    c["geh"] = geh(c["flow_method_vph"], c["flow_truth_vph"])
    assert detector_scores(c)["share_geh_below_5"] < 0.5
    assert detector_scores(pooled(c, 2))["share_geh_below_5"] == 1.0
