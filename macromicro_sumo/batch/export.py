"""Tables for spreadsheets and pandas: macro statistics of a finished run or batch, with
the variant's parameters as columns, as CSV or Parquet.

A batch folder (``batch.json``, one output folder per variant under ``variants/``) gives
``batch_macro``, ``batch_detectors`` and ``batch_summary``; a single run folder (the
output of ``macromicro simulate``) gives the same tables as a batch of one variant, named
``export_macro``, ``export_detectors`` and ``export_summary``. Variants may be ring or
section scenarios (each kind's ``simulate`` writes its own macro and detector columns; the
tables hold the union). The schema of every column is in docs/batch.md.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import MANIFEST, atomic_path, check_outputs, read_checked_csv, write_csv

FORMATS = ("csv", "parquet")
TABLES = ("macro", "detectors", "summary")
VARIANT_FILE = "variant.json"  # written into a variant's folder by the batch, with its params
SUMMARY_STATUS_COLUMNS = ["variant", "status", "reused", "wall_s", "error"]
HEADLINE_COLUMNS = [
    "n_runs",
    "n_intervals",
    "collisions",
    "teleports",
    "min_gap_m",
    "traj_mean_speed_mps",
    "det_mean_speed_mps",
    "det_speed_abs_error_mps",
    "traj_mean_spacing_m",
    "det_mean_spacing_m",
    "traj_density_vehpkm",
    "det_density_vehpkm",
    "traj_flow_vehph",
    "det_flow_vehph",
    "traj_vehicles",
    "det_vehicles",
    "k_mean_abs_error_veh",
]


def find_output(folder: Path, name: str) -> Path | None:
    """``folder/name`` (a stage's own folder), else the ground truth's of a whole-pipeline
    run (its deployment writes runs.csv and macro.csv too, one per method), else the first
    one below it."""
    for near in (folder / name, folder / "ground_truth" / name):
        if near.is_file():
            return near
    found = sorted(p for p in folder.rglob(name) if p.is_file())
    return found[0] if found else None


def _read(folder: Path, name: str, columns: Sequence[str] = ()) -> pd.DataFrame | None:
    """``name`` of a finished folder, checked against its manifest and for ``columns``;
    None where it has none."""
    path = find_output(folder, name)
    if path is None:
        return None
    return read_checked_csv(path.parent, path.name, columns=columns)


def damaged(folder: Path, rerun: str = "") -> str:
    """Why a finished folder's outputs are not what its manifests record ('' when they are):
    a listed file missing, or of another size or row count (sizes only, no hashing)."""
    for manifest in sorted(folder.rglob(MANIFEST)):
        if any(part.startswith(".") for part in manifest.relative_to(folder).parts):
            continue  # a stale staging folder's, not an output
        try:
            check_outputs(manifest.parent, deep=False, rerun=rerun)
        except UserError as exc:
            return str(exc)
    return ""


def _mean(df: pd.DataFrame, column: str) -> float:
    return float(df[column].mean()) if column in df else np.nan


def headline(folder: Path) -> dict[str, Any]:
    """Headline figures of one finished variant (NaN where its outputs lack them).

    Ring and section outputs differ: a section's ``macro.csv`` has a density per lane
    (``density_vpkm_lane``, reported as the density) and no flow (reported as density x
    speed, per lane, as the ring's trajectories do), plus vehicles on the section; its
    ``k_estimate.csv`` gives the hidden count's error. The ring's ``runs.csv`` alone has
    ``min_gap_m``.
    """
    out: dict[str, Any] = dict.fromkeys(HEADLINE_COLUMNS, np.nan)
    runs = _read(folder, "runs.csv")
    if runs is not None and not runs.empty:
        out["n_runs"] = len(runs)
        for col in ("collisions", "teleports"):
            if col in runs:
                out[col] = int(runs[col].sum())
        if "min_gap_m" in runs:
            out["min_gap_m"] = float(runs["min_gap_m"].min())
    k = _read(folder, "k_estimate.csv")
    if k is not None and not k.empty and "k_error" in k:
        out["k_mean_abs_error_veh"] = float(k["k_error"].abs().mean())
    m = _read(folder, "macro.csv", ("run", "source", "begin_s", "end_s", "mean_speed_mps"))
    if m is None or m.empty:
        return out
    density = "density_vehpkm" if "density_vehpkm" in m else "density_vpkm_lane"
    if "flow_vehph" not in m and density in m:
        m = m.assign(flow_vehph=m[density] * m["mean_speed_mps"] * 3.6)
    tr, de = m[m["source"] == "trajectories"], m[m["source"] == "detectors"]
    out["n_intervals"] = len(tr)
    for prefix, part in (("traj", tr), ("det", de)):
        out[f"{prefix}_mean_speed_mps"] = _mean(part, "mean_speed_mps")
        out[f"{prefix}_mean_spacing_m"] = _mean(part, "mean_spacing_m")
        out[f"{prefix}_density_vehpkm"] = _mean(part, density)
        out[f"{prefix}_flow_vehph"] = _mean(part, "flow_vehph")
        out[f"{prefix}_vehicles"] = _mean(part, "vehicles")
    both = tr.merge(de, on=["run", "begin_s", "end_s"], suffixes=("_t", "_d"))
    if not both.empty:
        out["det_speed_abs_error_mps"] = (
            (both["mean_speed_mps_d"] - both["mean_speed_mps_t"]).abs().mean()
        )
    return out


def _is_pair(value: Any) -> bool:
    """A [low, high] pair of numbers (a ring bound, ``bounds.accel_mps2``)."""
    return (
        isinstance(value, list | tuple)
        and len(value) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )


def param_columns(params: Sequence[dict[str, Any]]) -> dict[str, list[Any]]:
    """Sweep parameters as columns: one per dotted key, pairs of numbers split into
    ``.lo``/``.hi``, other lists (a section's ``section.edges``, ``network.route_files``)
    written as their items joined by spaces, as SUMO writes lists."""
    flat: list[dict[str, Any]] = []
    for p in params:
        row: dict[str, Any] = {}
        for key, value in p.items():
            if _is_pair(value):
                row[f"{key}.lo"], row[f"{key}.hi"] = value
            elif isinstance(value, list | tuple):
                row[key] = " ".join(str(v) for v in value)
            else:
                row[key] = value
        flat.append(row)
    keys: list[str] = []
    for row in flat:
        keys += [k for k in row if k not in keys]
    return {k: [row.get(k) for row in flat] for k in keys}


def _typed(values: list[Any]) -> pd.Series:
    """Integer parameters stay integers even where some variants lack them."""
    present = [v for v in values if v is not None]
    if present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        return pd.Series(values, dtype="Int64")
    return pd.Series([np.nan if v is None else v for v in values])


def _with_params(
    df: pd.DataFrame, variant: str, scenario: str, params: dict[str, list[Any]], i: int
) -> pd.DataFrame:
    head = {"variant": variant, "scenario": scenario}
    for key, values in params.items():
        head[key] = values[i]
    return pd.concat(
        [pd.DataFrame({k: [v] * len(df) for k, v in head.items()}), df.reset_index(drop=True)],
        axis=1,
    )


def gather(
    variants: Sequence[dict[str, Any]],
    statuses: dict[str, dict[str, Any]],
    variants_dir: Path,
    which: Sequence[str] = TABLES,
    headlines: dict[str, dict[str, Any]] | None = None,
) -> dict[str, pd.DataFrame]:
    """The tables ``which`` (of macro, detectors, summary) of a batch.

    ``variants``: spec rows with ``name``, ``scenario`` and ``params`` (dotted key -> value);
    ``statuses``: variant name -> the summary's status columns (status, reused, wall_s, error).
    Macro and detector rows come only from complete variants' folders. ``headlines``
    caches each complete variant's figures between calls.
    """
    headlines = {} if headlines is None else headlines
    params = param_columns([v["params"] for v in variants])
    macro, dets, summary = [], [], []
    for i, v in enumerate(variants):
        name = v["name"]
        st = {"status": "pending", "reused": False, "wall_s": np.nan, "error": ""}
        st.update(statuses.get(name, {}))
        folder = variants_dir / name
        figures = dict.fromkeys(HEADLINE_COLUMNS, np.nan)
        if st["status"] == "complete":
            if name not in headlines:
                headlines[name] = headline(folder)
            figures = headlines[name]
            for table, name_csv in ((macro, "macro.csv"), (dets, "detectors.csv")):
                if name_csv.removesuffix(".csv") not in which:
                    continue
                df = _read(folder, name_csv)
                if df is not None and not df.empty:
                    table.append(_with_params(df, name, v["scenario"], params, i))
        summary.append({"variant": name, **{k: st[k] for k in SUMMARY_STATUS_COLUMNS[1:]}})
        summary[-1].update({"scenario": v["scenario"], **figures})
    summary_df = pd.DataFrame(summary)
    for key, values in params.items():
        summary_df[key] = _typed(values)
    order = ["variant", "scenario", *params, *SUMMARY_STATUS_COLUMNS[1:], *HEADLINE_COLUMNS]
    summary_df = summary_df.reindex(columns=order)
    for col in ("collisions", "teleports", "n_runs", "n_intervals"):
        summary_df[col] = summary_df[col].astype("Int64")
    summary_df["reused"] = summary_df["reused"].astype(bool)
    tables = {
        "macro": _concat(macro, params) if "macro" in which else None,
        "detectors": _concat(dets, params) if "detectors" in which else None,
        "summary": summary_df,
    }
    return {k: v for k, v in tables.items() if k in which and v is not None}


def _concat(frames: list[pd.DataFrame], params: dict[str, list[Any]]) -> pd.DataFrame:
    if not frames:
        return pd.DataFrame(columns=["variant", "scenario", *params])
    df = pd.concat(frames, ignore_index=True)
    for key in params:
        values = df[key].tolist()
        df[key] = _typed([None if _missing(v) else v for v in values])
    return df


def _missing(v: Any) -> bool:
    return v is None or (isinstance(v, float) and np.isnan(v))


def write_tables(
    tables: dict[str, pd.DataFrame], folder: Path, prefix: str, fmt: str
) -> list[Path]:
    """Write ``<prefix>_<table>.<fmt>`` atomically; returns the paths written."""
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt!r} is not accepted; accepted: {', '.join(FORMATS)}")
    if fmt == "parquet":
        require_parquet()
    paths = []
    for name, df in tables.items():
        path = folder / f"{prefix}_{name}.{fmt}"
        if fmt == "csv":
            write_csv(df, path)
        else:
            with atomic_path(path) as tmp:
                df.to_parquet(tmp, index=False)
        paths.append(path)
    return paths


def require_parquet() -> None:
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise UserError(
            "Parquet export needs pyarrow: pip install 'macromicro-sumo[parquet]'"
        ) from None


def read_summary_statuses(path: Path) -> dict[str, dict[str, Any]]:
    """Status columns of an earlier ``batch_summary.csv`` (empty when there is none)."""
    if not path.is_file():
        return {}
    df = pd.read_csv(path, keep_default_na=False, dtype=str)
    out = {}
    for r in df.to_dict("records"):
        wall = r.get("wall_s", "")
        out[r["variant"]] = {
            "status": r.get("status", "") or "pending",
            "reused": r.get("reused", "") == "True",
            "wall_s": float(wall) if wall else np.nan,
            "error": r.get("error", ""),
        }
    return out


def export(folder: Path | str, fmt: str) -> list[Path]:
    """Re-export a finished batch or run folder; returns the files written."""
    folder = Path(folder)
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt!r} is not accepted; accepted: {', '.join(FORMATS)}")
    if fmt == "parquet":
        require_parquet()
    if (folder / "batch.json").is_file():
        spec = _read_json(folder / "batch.json")
        for v in spec["variants"]:
            v["params"] = dict(v["params"])  # stored as [key, value] pairs, in sweep order
        variants_dir = folder / "variants"
        statuses = read_summary_statuses(folder / "batch_summary.csv")
        for v in spec["variants"]:
            vfile = variants_dir / v["name"] / VARIANT_FILE
            if (variants_dir / v["name"] / "manifest.json").is_file() and vfile.is_file():
                # A finished variant's files must be the ones its manifest lists: one lost
                # or cut short would drop or garble its rows in the tables.
                rerun = f"re-run `macromicro batch` into {folder} (it redoes variant {v['name']})"
                problem = damaged(variants_dir / v["name"], rerun)
                if problem:
                    raise UserError(problem)
                info = _read_json(vfile)
                prev = statuses.get(v["name"], {})
                statuses[v["name"]] = {
                    "status": "complete",
                    "reused": prev.get("reused", False),
                    "wall_s": info.get("wall_s", np.nan),
                    "error": "",
                }
            elif statuses.get(v["name"], {}).get("status") == "complete":
                statuses[v["name"]] = {"status": "missing", "error": "output folder is gone"}
        return write_tables(gather(spec["variants"], statuses, variants_dir), folder, "batch", fmt)
    manifest = folder / "manifest.json"
    if manifest.is_file():
        m = _read_json(manifest)
        problem = damaged(folder)
        if problem:
            raise UserError(problem)
        wall = m.get("timings_s", {}).get(m.get("stage", ""), np.nan)
        spec = [{"name": folder.name, "scenario": m.get("scenario_name", ""), "params": {}}]
        statuses = {folder.name: {"status": "complete", "wall_s": wall}}
        tables = gather(spec, statuses, folder.parent)
        return write_tables(tables, folder, "export", fmt)
    raise UserError(
        f"{folder}: not a finished run or batch (no manifest.json or batch.json); "
        "pass the --out folder of `macromicro simulate` or `macromicro batch`"
    )


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable ({exc})") from None
