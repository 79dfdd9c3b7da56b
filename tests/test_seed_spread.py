"""scripts/seed_spread.py: several seeds' deploy_runs.py outputs compared run by run; the
split-half test says whether the seeds rank alike on different runs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("seed_spread", ROOT / "scripts" / "seed_spread.py")
ss = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ss)


def deploy_folder(folder: Path, rmse: list[float]) -> Path:
    """A deploy_runs.py output whose policy has speed RMSE ``rmse[r]`` on run r (the summary:
    their mean)."""
    folder.mkdir(parents=True)
    runs = pd.DataFrame(
        {"run": range(len(rmse)), "method": "policy", "speed_rmse_mps": rmse, "collisions": 0}
    )
    runs.to_csv(folder / "deploy_runs.csv", index=False)
    summary = pd.DataFrame({"method": ["policy"], "speed_rmse_mps": [sum(rmse) / len(rmse)]})
    summary.to_csv(folder / "deploy_summary.csv", index=False)
    return folder


def test_seeds_that_rank_alike_on_every_run_are_found_and_chosen(tmp_path: Path) -> None:
    # seed quality a property of the seed: the same order on all 4 runs
    table = pd.DataFrame(
        {
            f"s{i}": ss.per_run(
                deploy_folder(tmp_path / f"s{i}", [1 + i, 2 + i, 1.5 + i, 3 + i]), "policy"
            )
            for i in range(3)
        }
    ).T
    halves = ss.split_half(table)
    assert len(halves) == 6 and (halves["spearman"] == 1.0).all()
    # the best on any half (s0) is 1 m/s below the seeds' mean on the other
    assert halves["gain_mps"].tolist() == pytest.approx([1.0] * 6)
    assert table.loc["s1", "all"] == pytest.approx(2.875)


def test_seeds_whose_order_flips_between_runs_lose_by_choosing(tmp_path: Path) -> None:
    # runs 0 and 1 rank the seeds one way, runs 2 and 3 the other
    rmse = {"a": [1, 1, 3, 3], "b": [2, 2, 2, 2], "c": [3, 3, 1, 1]}
    table = pd.DataFrame(
        {k: ss.per_run(deploy_folder(tmp_path / k, v), "policy") for k, v in rmse.items()}
    ).T
    halves = ss.split_half(table).set_index(["first", "second"])
    assert halves.loc[("0 1", "2 3"), "spearman"] == pytest.approx(-1.0)
    assert halves.loc[("0 1", "2 3"), "gain_mps"] == pytest.approx(-1.0)  # a: 3 against 2


def test_the_command_prints_and_refuses_too_few_seeds(tmp_path: Path, capsys) -> None:
    folders = [
        deploy_folder(tmp_path / k, [1.0 + i, 2.0, 3.0 - i, 2.5]) for i, k in enumerate("xyz")
    ]
    assert ss.main([str(f) for f in folders] + ["--csv", str(tmp_path / "t.csv")]) == 0
    out = capsys.readouterr().out
    assert "split-half" in out and "mean Spearman" in out
    assert pd.read_csv(tmp_path / "t.csv", index_col=0).shape == (3, 5)
    with pytest.raises(SystemExit, match="at least 3 folders"):
        ss.main([str(f) for f in folders[:2]])
    with pytest.raises(SystemExit, match="no method 'idm'"):
        ss.main([str(f) for f in folders] + ["--method", "idm"])
