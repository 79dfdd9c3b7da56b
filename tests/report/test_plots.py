"""Evaluation figures: each writes one non-empty PNG atomically and nothing else."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from macromicro_sumo.evaluation.leader_follower import LeaderProfile, leader_speeds
from macromicro_sumo.report import plots

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RING_M = 628.3


def assert_only_png(folder: Path, name: str) -> None:
    """The folder holds exactly the PNG (no temporary left behind) and it is a real image."""
    assert sorted(p.name for p in folder.iterdir()) == [name]
    data = (folder / name).read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > 10_000


def lf_traces() -> pd.DataFrame:
    rng = np.random.default_rng(0)
    frames = []
    for scenario in ("accelerate", "decelerate"):
        lead = leader_speeds(scenario, LeaderProfile(), 0.5)
        t = np.arange(len(lead)) * 0.5
        idm = lead[0] + np.cumsum(np.r_[0.0, np.diff(lead)]) * 0.9
        for method, trials in (("IDM", 1), ("policy", 5)):
            for trial in range(trials):
                noise = 0 if method == "IDM" else np.cumsum(rng.normal(0, 0.03, len(t)))
                v = idm + noise
                frames.append(
                    pd.DataFrame(
                        {
                            "scenario": scenario,
                            "method": method,
                            "trial": trial,
                            "time_s": t,
                            "leader_speed_mps": lead,
                            "follower_speed_mps": v,
                            "idm_follower_speed_mps": idm,
                            "gap_m": 121.0 + np.cumsum(lead - v) * 0.5,
                        }
                    )
                )
    return pd.concat(frames, ignore_index=True)


def ring_trajectories(method: str, n: int, speed: float) -> pd.DataFrame:
    t = np.arange(0.0, 120.0, 0.5)
    frames = []
    for i in range(n):
        v = speed + 0.3 * np.sin(t / 10 + i)
        arc = np.mod(i * RING_M / n + np.cumsum(v) * 0.5, RING_M)
        frames.append(
            pd.DataFrame(
                {
                    "method": method,
                    "time_s": t,
                    "vehicle_id": f"v{i}",
                    "arc_pos_m": arc,
                    "speed_mps": v,
                }
            )
        )
    return pd.concat(frames, ignore_index=True)


def test_leader_follower_plot(tmp_path):
    out = plots.plot_leader_follower(lf_traces(), tmp_path / "leader_follower.png")
    assert out == tmp_path / "leader_follower.png"
    assert_only_png(tmp_path, "leader_follower.png")


def test_leader_follower_plot_from_csv_replaces_old_file(tmp_path):
    csv = tmp_path / "in" / "leader_follower.csv"
    csv.parent.mkdir()
    lf_traces().to_csv(csv, index=False)
    png = tmp_path / "out" / "lf.png"
    png.parent.mkdir()
    png.write_bytes(b"old")
    plots.plot_leader_follower(csv, png)
    assert_only_png(png.parent, "lf.png")


def test_time_space_plot(tmp_path):
    df = pd.concat(
        [ring_trajectories("ground_truth", 5, 12.0), ring_trajectories("policy", 5, 12.5)]
    ).rename(columns={"arc_pos_m": "arc_m"})
    sources = {m: g for m, g in df.groupby("method")}
    plots.plot_time_space(sources, tmp_path / "time_space.png", length_m=RING_M)
    assert_only_png(tmp_path, "time_space.png")


def test_lane_segments_skip_the_wrap_and_join_no_two_vehicles():
    t = np.array([0.0, 1.0, 2.0, 3.0, 0.0, 1.0, 2.0])
    x = np.array([600.0, 612.0, 624.0, 8.0, 100.0, 112.0, 124.0])  # a wraps after t = 2
    ids = ["a"] * 4 + ["b"] * 2 + ["c"]  # c's one row joins nothing
    g = pd.DataFrame({"time_s": t, "arc_m": x, "speed_mps": 12.0, "vehicle_id": ids})
    segs, speeds = plots.lane_segments(g, max_dt_s=1.5)
    assert len(segs) == len(speeds) == 3
    assert (segs[:, 1, 1] >= segs[:, 0, 1]).all()  # no segment runs backwards
    assert (segs[:, 1, 0] > segs[:, 0, 0]).all()
    np.testing.assert_array_equal(segs[:, 0, 1], [600.0, 612.0, 100.0])
    # A gap longer than max_dt_s (the vehicle left the lane meanwhile) is not drawn.
    assert len(plots.lane_segments(g, max_dt_s=0.5)[0]) == 0


@pytest.mark.parametrize("by_k", [False, True])
def test_distribution_plot(tmp_path, by_k):
    rng = np.random.default_rng(1)
    n = 2000
    df = pd.concat(
        [
            pd.DataFrame(
                {
                    "method": "ground_truth",
                    "K": np.nan,
                    "speed_mps": rng.normal(12.0, 0.5, n),
                    "spacing_m": rng.normal(125.7, 32, n),
                }
            ),
            pd.DataFrame(
                {
                    "method": "policy",
                    "K": rng.integers(1, 5, n),
                    "speed_mps": rng.normal(12.0, 0.6, n),
                    "spacing_m": rng.normal(125.7, 33, n),
                }
            ),
        ]
    )
    plots.plot_distributions(df, tmp_path / "dist.png", by_k=by_k)
    assert_only_png(tmp_path, "dist.png")


def test_training_plots(tmp_path):
    epochs = np.arange(30)
    gen = {"epoch": epochs}
    for split in ("train", "val"):
        terms = {
            f"{split}_L_{k}": np.exp(-epochs / 10) * s for k, s in (("speed", 1e-3), ("var", 0.3))
        }
        gen |= terms | {f"{split}_loss": sum(terms.values())}
    plots.plot_generator_training(pd.DataFrame(gen), tmp_path / "gen" / "generator_training.png")
    assert_only_png(tmp_path / "gen", "generator_training.png")
    upd = np.arange(1, 21)
    pol = pd.DataFrame(
        {
            "update": upd,
            "r_macro": 0.95 + 0.001 * upd,
            "r_micro_per_pair": np.log(upd),
            "pg_loss": np.sin(upd) / 10,
            "v_loss": np.exp(-upd / 5),
            "kl": 0.01 + 0.0 * upd,
            "action_std_mps2": 0.35 * np.exp(-upd / 10),
        }
    )
    csv = tmp_path / "policy_train_log.csv"
    pol.to_csv(csv, index=False)
    plots.plot_policy_training(csv, tmp_path / "pol" / "policy_training.png")
    assert_only_png(tmp_path / "pol", "policy_training.png")


def test_bad_input_writes_nothing(tmp_path):
    with pytest.raises(ValueError, match="missing columns gap_m"):
        plots.plot_leader_follower(lf_traces().drop(columns="gap_m"), tmp_path / "x.png")
    with pytest.raises(ValueError, match="no rows"):
        empty = ring_trajectories("gt", 2, 12.0).rename(columns={"arc_pos_m": "arc_m"}).iloc[:0]
        plots.plot_time_space({"gt": empty}, tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []
