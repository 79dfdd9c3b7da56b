"""A deployment's detectors against the ground truth's, station by station and interval by
interval: deploy_comparison.csv and deploy_summary.csv (definitions: docs/deploy.md).

A deployment folder holds the ground truth's files in the ground truth's schemas
(detectors.csv, trajectories.csv, runs.csv, ...) for the held-out runs; the truth folder
holds every run. They are compared on the runs both have, matched by run number, station,
lane and interval.

A ground truth read from field files (its manifest's ``data_source = "files"``) is only what
was measured, and the summary's ``reference`` says so: the detector figures are against the
field stations, from ``simulation.warmup_s`` on (a deployment's SUMO run starts with an
empty road and fills it first); the distributions are of speed and acceleration against
the observed vehicles (a sample of the population), and headway and time-to-collision are
not compared (NaN: whoever drove between two observed vehicles is unknown).

The station-intervals are of ``deploy.compare_interval_s`` (0: the detectors' own interval;
else the detectors' intervals pooled, ``deploy.intervals``); the summary also keeps the
detector-interval shares (``*_detector_interval``). The statistics are pure functions on
DataFrames; ``compare_folders`` reads the folders and ``write_comparison`` writes the two CSVs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.deploy.distributions import (
    LANE_COLUMNS,
    distribution_distances,
    lane_trajectories,
)
from macromicro_sumo.deploy.intervals import KEY, block_factor, interval_length_s, pool_detectors
from macromicro_sumo.deploy.population import SAFETY_COLUMNS
from macromicro_sumo.deploy.stations import (
    ALL_LANES,
    KEYS,
    station_table,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import read_manifest, write_csv
from macromicro_sumo.road.section import Section

GEH_LIMIT = 5.0  # DMRB acceptance: GEH < 5 for more than 85% of the counts
SPEED_TOLERANCE = 0.05  # |method - truth| / truth within 5%
COMPARISON_COLUMNS = [
    "method",
    *KEYS,
    "arc_m",
    "flow_truth_vph",
    "flow_method_vph",
    "geh",
    "speed_truth_mps",
    "speed_method_mps",
    "speed_rel_error",
    "density_truth_vpkm",
    "density_method_vpkm",
]
# How often the safety layer acted, as shares of the driven vehicle-steps: it lowered a
# command (safe speed) or raised one to its floor (``deploy.safety.FLOOR_SHARE``).
ACTED_SHARES = {"safety_acted_share": "safety_acted", "floor_acted_share": "floor_acted"}
REFERENCE_SIMULATED = "ground truth: every vehicle (simulated)"
REFERENCE_FIELD = "field: stations (detectors), observed vehicles (speed, accel)"
# The detector-interval figures kept beside those at deploy.compare_interval_s.
AT_DETECTORS = (
    "station_intervals",
    "share_geh_below_5",
    "share_speed_within_5pct",
    "speed_rmse_mps",
)
DETECTOR_INTERVAL_COLUMNS = {c: f"{c}_detector_interval" for c in AT_DETECTORS}
SUMMARY_COLUMNS = [
    "method",
    "reference",
    "runs",
    "compare_interval_s",
    "detector_interval_s",
    "station_intervals",
    "share_geh_below_5",
    "share_speed_within_5pct",
    "mean_geh",
    "speed_rmse_mps",
    "speed_bias_mps",
    "density_rmse_vpkm",
    *DETECTOR_INTERVAL_COLUMNS.values(),
    "w1_speed_mps",
    "w1_accel_mps2",
    "w1_headway_s",
    "w1_ttc_s",
    *SAFETY_COLUMNS,
    *ACTED_SHARES,
    "safety",
    "safety_floor_share",
    "truth_collisions",
    "truth_teleports",
]


# --------------------------------------------------------------------------- statistics


def geh(model_vph: np.ndarray, count_vph: np.ndarray) -> np.ndarray:
    """GEH statistic of modelled against counted flows, both in veh/h.

    GEH = sqrt(2 (M - C)^2 / (M + C)) (Geoffrey E. Havers, 1970s; the calibration
    criterion of the UK Design Manual for Roads and Bridges, Vol. 12 Sec. 2 Part 1, and of
    TAG unit M3.1: GEH < 5 for more than 85% of hourly link flows). An interval's count
    enters as its hourly rate (n veh in 60 s -> 60 n veh/h), as SUMO's loops write it:
    shorter intervals make the test stricter, not looser. Both zero: GEH 0 (agreement).
    NaN where either flow is missing (a lane-area detector measures no flow).
    """
    m = np.asarray(model_vph, dtype=float)
    c = np.asarray(count_vph, dtype=float)
    total = m + c
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.sqrt(2.0 * (m - c) ** 2 / total)
    return np.where(total == 0, 0.0, g)


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square of a - b over the pairs where both are finite (NaN: none)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def relative_error(method: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(method - truth) / truth; NaN where either is missing or the truth is 0."""
    m, t = np.asarray(method, dtype=float), np.asarray(truth, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(t > 0, (m - t) / t, np.nan)


# The scores of ``detector_scores`` that the scripts print, in the order they print them.
HEADLINE_SCORES = (
    "station_intervals",
    "share_geh_below_5",
    "share_speed_within_5pct",
    "speed_rmse_mps",
    "speed_bias_mps",
)


def detector_scores(comparison: pd.DataFrame) -> dict[str, float]:
    """Summary of station-intervals (rows with ``lane == ALL_LANES``) of a comparison.

    Shares count agreements over the station-intervals where the quantity was measured:
    GEH over those with a flow on both sides (both zero counts as GEH 0); speed within
    ``SPEED_TOLERANCE`` over those where either side has a speed (a speed on one side only
    -- vehicles passed in one run and not in the other -- is a miss). RMSEs are over the
    intervals with both values.
    """
    s = comparison[comparison["lane"] == ALL_LANES]
    g = s["geh"].to_numpy(dtype=float)
    g = g[np.isfinite(g)]
    vt = s["speed_truth_mps"].to_numpy(dtype=float)
    vm = s["speed_method_mps"].to_numpy(dtype=float)
    rel = relative_error(vm, vt)
    measured = np.isfinite(vt) | np.isfinite(vm)
    within = np.isfinite(rel) & (np.abs(rel) <= SPEED_TOLERANCE + 1e-12)
    both = np.isfinite(vt) & np.isfinite(vm)
    return {
        "station_intervals": len(s),
        "share_geh_below_5": float(np.mean(g < GEH_LIMIT)) if g.size else np.nan,
        "share_speed_within_5pct": float(within[measured].mean()) if measured.any() else np.nan,
        "mean_geh": float(g.mean()) if g.size else np.nan,
        "speed_rmse_mps": rmse(vm, vt),
        "speed_bias_mps": float(np.mean(vm[both] - vt[both])) if both.any() else np.nan,
        "density_rmse_vpkm": rmse(s["density_method_vpkm"], s["density_truth_vpkm"]),
    }


def safety_counts(runs: pd.DataFrame, keep: list[int]) -> dict[str, float]:
    """Sums of ``SAFETY_COLUMNS`` of ``runs.csv`` over the runs ``keep`` (NaN: not recorded)."""
    r = runs[runs["run"].isin(keep)]
    return {
        c: float(r[c].sum()) if c in r.columns and r[c].notna().any() else np.nan
        for c in SAFETY_COLUMNS
    }


def acted_shares(counts: Mapping[str, float]) -> dict[str, float]:
    """``ACTED_SHARES`` of ``safety_counts``: each count over the driven vehicle-steps
    (NaN where nothing was driven or the count was not recorded)."""
    driven = counts["vehicle_steps_driven"]
    ok = np.isfinite(driven) and driven > 0
    return {k: counts[c] / driven if ok else np.nan for k, c in ACTED_SHARES.items()}


def comparison_table(truth: pd.DataFrame, method: pd.DataFrame, name: str) -> pd.DataFrame:
    """Rows of deploy_comparison.csv: ``station_table`` rows of truth and method matched on
    run, station, lane and interval (the runs and intervals both have)."""
    m = truth.merge(method, on=KEYS, suffixes=("_truth", "_method"), how="inner")
    out = pd.DataFrame(
        {
            "method": name,
            **{k: m[k] for k in KEYS},
            "arc_m": m["arc_m_truth"],
            "flow_truth_vph": m["flow_vph_truth"],
            "flow_method_vph": m["flow_vph_method"],
            "geh": geh(m["flow_vph_method"], m["flow_vph_truth"]),
            "speed_truth_mps": m["speed_mps_truth"],
            "speed_method_mps": m["speed_mps_method"],
            "speed_rel_error": relative_error(m["speed_mps_method"], m["speed_mps_truth"]),
            "density_truth_vpkm": m["density_vpkm_truth"],
            "density_method_vpkm": m["density_vpkm_method"],
        }
    )
    return out.reindex(columns=COMPARISON_COLUMNS)


# --------------------------------------------------------------------------- folders


@dataclass(frozen=True)
class Outputs:
    """What the comparison reads of one folder (ground truth or one method's deployment)."""

    folder: Path
    stations: pd.DataFrame  # station_table
    runs: pd.DataFrame  # runs.csv (may lack SAFETY_COLUMNS)
    lanes: pd.DataFrame  # trajectories in lane_trajectories' schema (may be empty)
    detectors: pd.DataFrame  # detectors.csv as read (pooled into longer intervals on demand)

    def stations_at(self, k: int) -> pd.DataFrame:
        """``station_table`` with the detectors' intervals pooled in blocks of k."""
        return self.stations if k == 1 else station_table(pool_detectors(self.detectors, k))


@dataclass(frozen=True)
class Geometry:
    """What leaders on a section need: the section and the vTypes' lengths (ring: none)."""

    section: Section | None = None
    vehicle_lengths_m: Mapping[str, float] | None = None


def read_table(folder: Path, name: str, required: bool = True, **kwargs: object) -> pd.DataFrame:
    path = folder / name
    if not path.is_file():
        if required:
            raise UserError(f"{path}: missing (a ground-truth or deploy folder holds it)")
        return pd.DataFrame()
    try:
        return pd.read_csv(path, **kwargs)
    except ValueError as exc:
        raise UserError(f"{path}: not a readable CSV ({type(exc).__name__}: {exc})") from None


def truth_geometry(folder: Path | str) -> Geometry:
    """The section of a section's ground truth (section.json, vtypes.csv); nothing on a ring."""
    folder = Path(folder)
    if not (folder / "section.json").is_file():
        return Geometry()
    vt = read_table(folder, "vtypes.csv", required=False, dtype={"vtype": str})
    lengths = dict(zip(vt["vtype"], vt["length_m"], strict=True)) if len(vt) else {}
    return Geometry(Section.read(folder / "section.json"), lengths)


def read_outputs(folder: Path | str, geometry: Geometry, leaders: bool = True) -> Outputs:
    """detectors.csv as stations, runs.csv, and trajectories.csv (if there; with each
    vehicle's leader unless not ``leaders``)."""
    folder = Path(folder)
    det = read_table(folder, "detectors.csv")
    if det.empty:
        raise UserError(f"{folder / 'detectors.csv'}: no detector interval")
    runs = read_table(folder, "runs.csv", required=False)
    traj = read_table(
        folder, "trajectories.csv", required=False, dtype={"vehicle_id": str, "vtype": str}
    )
    lanes = (
        lane_trajectories(traj, geometry.section, geometry.vehicle_lengths_m, leaders)
        if len(traj)
        else pd.DataFrame(columns=list(LANE_COLUMNS))
    )
    if runs.empty:
        runs = pd.DataFrame({"run": sorted(det["run"].unique())})
    return Outputs(folder, station_table(det), runs, lanes, det)


@dataclass(frozen=True)
class Reference:
    """What a ground-truth folder can be compared with: ``field`` data (stations and the
    observed vehicles) from ``from_s`` on, or a simulated truth (every vehicle, all times)."""

    field: bool = False
    from_s: float = 0.0

    @property
    def label(self) -> str:
        return REFERENCE_FIELD if self.field else REFERENCE_SIMULATED


def truth_reference(folder: Path | str) -> Reference:
    """A field-data truth (manifest ``data_source = "files"``) or a simulated one."""
    path = Path(folder) / "manifest.json"
    manifest = read_manifest(path) if path.is_file() else {}
    if manifest.get("data_source") != "files":
        return Reference()
    warmup = manifest.get("scenario", {}).get("simulation", {}).get("warmup_s", 0.0)
    return Reference(True, float(warmup))


def safety_layer(folder: Path) -> tuple[str, float | None]:
    """(safety layer, its floor share) a method's manifest.json records: ("sumo", 0.2) or
    ("none", None) for a speed-commanding method; ("", None) for the others and a folder
    without a manifest."""
    path = folder / "manifest.json"
    manifest = read_manifest(path) if path.is_file() else {}
    return str(manifest.get("safety") or ""), manifest.get("safety_floor_share")


def summary_row(
    name: str,
    truth: Outputs,
    method: Outputs,
    comparison: pd.DataFrame,
    reference: Reference | None = None,
    at_detectors: pd.DataFrame | None = None,
) -> dict:
    """One row of deploy_summary.csv: ``method`` against ``truth`` on the runs of
    ``comparison`` (``comparison_table`` of both sides' ``stations_at`` the comparison
    interval); ``at_detectors``: the same at the detectors' interval (None: ``comparison``
    is at it)."""
    runs = sorted(int(r) for r in comparison["run"].unique())
    lanes = method.lanes[method.lanes["run"].isin(runs)]
    dist = (
        distribution_distances(truth.lanes, lanes)
        if len(lanes) and len(truth.lanes)
        else {f"w1_{k}": np.nan for k in ("speed_mps", "accel_mps2", "headway_s", "ttc_s")}
    )
    truth_safety = safety_counts(truth.runs, runs)
    safety = safety_counts(method.runs, runs)
    layer, floor = safety_layer(method.folder)
    at = detector_scores(comparison if at_detectors is None else at_detectors)
    return {
        "method": name,
        "reference": (reference or Reference()).label,
        "runs": len(runs),
        "compare_interval_s": interval_length_s(comparison),
        "detector_interval_s": interval_length_s(
            comparison if at_detectors is None else at_detectors
        ),
        **detector_scores(comparison),
        **{col: at[c] for c, col in DETECTOR_INTERVAL_COLUMNS.items()},
        **dist,
        **safety,
        **acted_shares(safety),
        "safety": layer,
        "safety_floor_share": np.nan if floor is None else float(floor),
        "truth_collisions": truth_safety["collisions"],
        "truth_teleports": truth_safety["teleports"],
    }


def compare_folders(
    truth_dir: Path | str, method_dirs: Mapping[str, Path | str], compare_interval_s: float = 0.0
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(deploy_comparison, deploy_summary) of every method's folder against the truth's, at
    ``compare_interval_s`` (``deploy.compare_interval_s``; 0: the detectors' interval)."""
    geometry = truth_geometry(truth_dir)
    ref = truth_reference(truth_dir)
    # Field data: leaders among the observed vehicles are not the vehicles' leaders.
    truth = read_outputs(truth_dir, geometry, leaders=not ref.field)
    where = Path(truth_dir) / "detectors.csv"
    k = block_factor(compare_interval_s, interval_length_s(truth.detectors), str(where))

    def after_warmup(st: pd.DataFrame) -> pd.DataFrame:
        return st[st["begin_s"] >= ref.from_s - 1e-9] if ref.field else st

    truth_st, truth_at = after_warmup(truth.stations), after_warmup(truth.stations_at(k))
    tables, rows = [], []
    for name, folder in method_dirs.items():
        method = read_outputs(folder, geometry)
        at_detectors = comparison_table(truth_st, method.stations, name)
        if at_detectors.empty:
            raise UserError(
                f"{folder}: no run, station and interval in common with the ground truth "
                f"{truth_dir} (another scenario, or other runs?)"
            )
        comp = at_detectors if k == 1 else comparison_table(truth_at, method.stations_at(k), name)
        if comp.empty:
            raise UserError(
                f"{where}: {KEY} = {compare_interval_s:g} leaves no whole interval of "
                f"{compare_interval_s:g} s in the runs compared; accepted: at most a run's length"
            )
        tables.append(comp)
        rows.append(summary_row(name, truth, method, comp, ref, at_detectors))
    comparison = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    return comparison.reindex(columns=COMPARISON_COLUMNS), pd.DataFrame(
        rows, columns=SUMMARY_COLUMNS
    )


def write_comparison(
    truth_dir: Path | str,
    method_dirs: Mapping[str, Path | str],
    out_dir: Path | str,
    compare_interval_s: float = 0.0,
) -> tuple[Path, Path]:
    """Write deploy_comparison.csv and deploy_summary.csv into ``out_dir``; their paths."""
    out = Path(out_dir)
    comparison, summary = compare_folders(truth_dir, method_dirs, compare_interval_s)
    paths = out / "deploy_comparison.csv", out / "deploy_summary.csv"
    write_csv(comparison, paths[0])
    write_csv(summary, paths[1])
    return paths
