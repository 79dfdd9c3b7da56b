"""``macromicro export``: CSV and Parquet tables of a finished batch or run, and the
schema in docs/batch.md against the columns actually written."""

from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path

import pandas as pd
import pytest
from conftest import ROOT, SMALL, dump_toml, scenario_table, write_scenario

from macromicro_sumo.batch.export import find_output, headline
from macromicro_sumo.batch.runner import run_batch
from macromicro_sumo.cli import main

TABLES = ("macro", "detectors", "summary")


@pytest.fixture(scope="module")
def finished_batch(tmp_path_factory) -> Path:
    """Four variants, two of them failed (130 vehicles do not fit on the ring)."""
    folder = tmp_path_factory.mktemp("batch")
    table = scenario_table({"simulation.n_runs": 1, "simulation.duration_s": 120.0})
    path = folder / "s.toml"
    path.write_text(dump_toml(table) + '\n[sweep]\nseed = [1, 2]\n"fleet.n_vehicles" = [5, 130]\n')
    run_batch([path], folder / "out", workers=2, progress=False)
    return folder / "out"


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("run")
    path = write_scenario(folder, SMALL)
    assert main(["simulate", str(path), "--out", str(folder / "gt"), "--quiet"]) == 0
    return folder / "gt"


def test_csv_export_of_a_batch_rewrites_the_same_bytes(finished_batch, tmp_path):
    before = {t: (finished_batch / f"batch_{t}.csv").read_bytes() for t in TABLES}
    for t in TABLES:
        (finished_batch / f"batch_{t}.csv").unlink()
    (finished_batch / "batch_summary.csv").write_bytes(before["summary"])  # statuses live here
    assert main(["export", str(finished_batch), "--format", "csv"]) == 0
    after = {t: (finished_batch / f"batch_{t}.csv").read_bytes() for t in TABLES}
    assert after == before


def test_batch_tables_shape(finished_batch):
    s = pd.read_csv(finished_batch / "batch_summary.csv")
    assert s["status"].value_counts().to_dict() == {"complete": 2, "failed": 2}
    failed = s[s["status"] == "failed"]
    assert failed["error"].str.contains("does not fit").all()
    assert failed["traj_mean_speed_mps"].isna().all()
    macro = pd.read_csv(finished_batch / "batch_macro.csv")
    assert set(macro["variant"]) == set(s.loc[s["status"] == "complete", "variant"])
    assert len(macro) == 2 * 1 * 2 * 2  # complete variants x runs x sources x intervals
    assert macro["fleet.n_vehicles"].eq(5).all()


def test_parquet_export_holds_the_same_tables(finished_batch):
    pytest.importorskip("pyarrow")
    assert main(["export", str(finished_batch), "--format", "parquet"]) == 0
    for t in TABLES:
        pq = pd.read_parquet(finished_batch / f"batch_{t}.parquet")
        csv = pd.read_csv(finished_batch / f"batch_{t}.csv")
        assert list(pq.columns) == list(csv.columns)
        assert len(pq) == len(csv)
    pq = pd.read_parquet(finished_batch / "batch_macro.parquet")
    csv = pd.read_csv(finished_batch / "batch_macro.csv")
    pd.testing.assert_series_equal(pq["mean_speed_mps"].round(6), csv["mean_speed_mps"])


def test_parquet_without_pyarrow_says_how_to_install(finished_batch, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # as if not installed
    code = main(["export", str(finished_batch), "--format", "parquet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert "pip install 'macromicro-sumo[parquet]'" in err


def test_export_of_a_single_run(finished_run):
    assert main(["export", str(finished_run)]) == 0
    macro = pd.read_csv(finished_run / "export_macro.csv")
    own = pd.read_csv(finished_run / "macro.csv")
    assert len(macro) == len(own)
    assert (macro["variant"] == finished_run.name).all()
    pd.testing.assert_frame_equal(macro.drop(columns=["variant", "scenario"]), own)
    s = pd.read_csv(finished_run / "export_summary.csv")
    assert s["status"].tolist() == ["complete"] and s["n_runs"].tolist() == [2]


def test_export_of_anything_else_is_a_one_line_error(tmp_path, capsys):
    code = main(["export", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1
    assert "not a finished run or batch" in err


def export_fails(capsys, folder: Path, *fragments: str) -> str:
    """``macromicro export folder`` refused in one line; no table written."""
    before = sorted(p.name for p in folder.iterdir())
    code = main(["export", str(folder)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    assert sorted(p.name for p in folder.iterdir()) == before
    return err


def test_export_of_a_run_with_a_truncated_macro_csv_names_it(finished_run, tmp_path, capsys):
    copy = tmp_path / "gt"
    shutil.copytree(finished_run, copy)
    data = (copy / "macro.csv").read_bytes()
    (copy / "macro.csv").write_bytes(data[: data.index(b"\n") + 5])  # header + 4 bytes
    export_fails(capsys, copy, f"{copy / 'macro.csv'}: 1 data rows", "re-run `macromicro simulate`")


def test_a_batch_variant_without_macro_csv_is_refused_then_redone(finished_batch, tmp_path, capsys):
    copy = tmp_path / "out"
    shutil.copytree(finished_batch, copy)
    summary = pd.read_csv(copy / "batch_summary.csv")
    name = summary.loc[summary["status"] == "complete", "variant"].iloc[0]
    (copy / "variants" / name / "macro.csv").unlink()
    export_fails(
        capsys,
        copy,
        f"{copy / 'variants' / name / 'macro.csv'}: missing",
        f"re-run `macromicro batch` into {copy} (it redoes variant {name})",
    )
    # The re-run sees the variant as unfinished and redoes it (and only it).
    res = run_batch([finished_batch.parent / "s.toml"], copy, workers=1, progress=False)
    assert res.counts["reused"] == 1 and res.counts["complete"] == 2
    assert (copy / "variants" / name / "macro.csv").is_file()
    assert main(["export", str(copy)]) == 0
    macro = pd.read_csv(copy / "batch_macro.csv")
    assert (macro["variant"] == name).sum() == 4  # runs x sources x intervals


def documented_columns(table: str) -> list[str]:
    """Column names listed in docs/batch.md under the heading for ``table``."""
    text = (ROOT / "docs" / "batch.md").read_text()
    section = text.split(f"### `{table}`", 1)[1].split("\n### ", 1)[0]
    return re.findall(r"^\| `([^`]+)` \|", section, flags=re.M)


@pytest.mark.parametrize("table", TABLES)
def test_every_column_is_documented(finished_batch, table):
    written = list(pd.read_csv(finished_batch / f"batch_{table}.csv", nrows=0).columns)
    params = {"seed", "fleet.n_vehicles"}  # this sweep's parameter columns
    documented = documented_columns(f"batch_{table}")
    assert documented, "no column table found in docs/batch.md"
    assert [c for c in written if c not in params] == documented


def test_a_pipeline_runs_headline_figures_are_its_ground_truths(finished_run, tmp_path):
    """A whole-pipeline variant holds runs.csv and macro.csv per deployed method too (one
    held-out run each): the headline figures are the ground truth's, all of its runs."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run / "ground_truth")
    deployed = run / "deploy" / "policy"
    deployed.mkdir(parents=True)
    truth_runs = pd.read_csv(run / "ground_truth" / "runs.csv")
    truth_runs.iloc[:1].to_csv(deployed / "runs.csv", index=False)
    assert len(truth_runs) > 1
    assert find_output(run, "runs.csv") == run / "ground_truth" / "runs.csv"
    assert headline(run)["n_runs"] == len(truth_runs)
