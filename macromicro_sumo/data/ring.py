"""Dataset: partially observed snapshots (and micro pairs) built from a ground-truth folder.

A snapshot is the whole ring at one instant (arc position and speed of all N vehicles),
a hidden mask (K vehicles the generator must complete; their true states are kept for
evaluation only) and the macro descriptor Psi of the snapshot's detector interval.
Runs are split into train / validation / held-out, so held-out snapshots come from runs
never seen in training.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.macro import PSI_COLUMNS, extended_bounds
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import read_checked_csv, read_manifest
from macromicro_sumo.scenario.ring import Scenario

GT_FILES = ("trajectories.csv", "macro.csv", "vehicles.csv", "speed_limits.csv", "manifest.json")

# The columns later stages read (see docs/design.md for each file's whole schema) and those
# that must hold finite numbers: a NaN in a state or a parameter would surface stages later.
TRAJECTORY_COLUMNS = (
    "run",
    "time_s",
    "vehicle_id",
    "arc_pos_m",
    "theta_rad",
    "speed_mps",
    "accel_mps2",
    "leader_id",
    "spacing_m",
    "gap_m",
    "leader_speed_mps",
    "speed_limit_mps",
)
TRAJECTORY_NUMBERS = tuple(c for c in TRAJECTORY_COLUMNS if c not in ("vehicle_id", "leader_id"))
MACRO_COLUMNS = ("run", "source", "begin_s", "end_s", *PSI_COLUMNS, "spacing_std_m", "n_samples")
VEHICLE_COLUMNS = (
    "run",
    "vehicle_id",
    "accel_mps2",
    "decel_mps2",
    "tau_s",
    "min_gap_m",
    "delta",
    "speed_factor",
    "max_speed_mps",
    "length_m",
)
LIMIT_COLUMNS = ("run", "edge_id", "speed_limit_mps")


@dataclass(frozen=True)
class GroundTruth:
    folder: Path
    trajectories: pd.DataFrame
    macro: pd.DataFrame
    vehicles: pd.DataFrame
    speed_limits: pd.DataFrame
    manifest: dict

    @property
    def runs(self) -> np.ndarray:
        return np.sort(self.trajectories["run"].unique())


def load_ground_truth(folder: Path | str, sc: Scenario | None = None) -> GroundTruth:
    """Read a ``simulate`` output folder; missing files and scenario mismatches are errors."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(
            f"{folder}: ground-truth folder not found (run `macromicro simulate` first)"
        )
    missing = [f for f in GT_FILES if not (folder / f).is_file()]
    if missing:
        raise UserError(f"{folder}: ground-truth folder is missing {', '.join(missing)}")
    manifest = read_manifest(folder / "manifest.json")
    if sc is not None:
        got = manifest.get("scenario")
        got = got if isinstance(got, dict) else {}
        for table, key in (
            ("fleet", "n_vehicles"),
            ("network", "radius_m"),
            ("simulation", "step_length_s"),
        ):
            want = getattr(getattr(sc, table), key)
            sub = got.get(table)
            have = sub.get(key) if isinstance(sub, dict) else None
            if have != want:
                raise UserError(
                    f"{folder}: ground truth was simulated with {table}.{key} = {have}, "
                    f"scenario {sc.source} has {want}"
                )
    # Each CSV is checked against the manifest's outputs map (rows and SHA-256): a file
    # cut short or edited after `simulate` wrote it is refused, not half-used.
    return GroundTruth(
        folder=folder,
        trajectories=read_checked_csv(
            folder,
            "trajectories.csv",
            manifest,
            TRAJECTORY_COLUMNS,
            TRAJECTORY_NUMBERS,
        ),
        macro=read_checked_csv(folder, "macro.csv", manifest, MACRO_COLUMNS, ("run",)),
        vehicles=read_checked_csv(
            folder,
            "vehicles.csv",
            manifest,
            VEHICLE_COLUMNS,
            [c for c in VEHICLE_COLUMNS if c != "vehicle_id"],
        ),
        speed_limits=read_checked_csv(
            folder,
            "speed_limits.csv",
            manifest,
            LIMIT_COLUMNS,
            ("run", "speed_limit_mps"),
        ),
        manifest=manifest,
    )


def split_runs(
    runs: np.ndarray, held_out_fraction: float, seed: int, val_fraction: float = 0.15
) -> dict[str, np.ndarray]:
    """Disjoint train / val / held_out run ids (seeded shuffle); val drives early stopping."""
    rng = np.random.default_rng([seed, 7])
    perm = rng.permutation(runs)
    n_held = max(1, int(round(held_out_fraction * len(runs))))
    n_val = max(1, int(round(val_fraction * len(runs)))) if len(runs) - n_held >= 2 else 0
    if len(runs) - n_held - n_val < 1:
        raise UserError(
            f"need at least 2 ground-truth runs to split train / held-out, got {len(runs)}"
        )
    return {
        "held_out": np.sort(perm[:n_held]),
        "val": np.sort(perm[n_held : n_held + n_val]),
        "train": np.sort(perm[n_held + n_val :]),
    }


@dataclass(frozen=True)
class Snapshots:
    """A batch of ring snapshots, arrays over (B,) or (B, N)."""

    run: np.ndarray
    time_s: np.ndarray
    arc_m: np.ndarray
    speed_mps: np.ndarray
    psi: np.ndarray  # (B, 6) in PSI_COLUMNS order
    hidden: np.ndarray  # (B, N) bool
    length_m: float
    # The detectors' spacing std per snapshot [m], present when the scenario asks the
    # generator to match the measured dispersion (generator.spacing_dispersion = "measured").
    spacing_std_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.run)

    @property
    def k(self) -> np.ndarray:
        return self.hidden.sum(axis=1)

    def take(self, idx: np.ndarray) -> Snapshots:
        return replace(
            self,
            run=self.run[idx],
            time_s=self.time_s[idx],
            arc_m=self.arc_m[idx],
            speed_mps=self.speed_mps[idx],
            psi=self.psi[idx],
            hidden=self.hidden[idx],
            spacing_std_m=None if self.spacing_std_m is None else self.spacing_std_m[idx],
        )


def run_arrays(
    traj: pd.DataFrame, run: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(times (T,), arc (T, N), speed (T, N), vehicle ids) of one run."""
    g = traj[traj["run"] == run]
    ids = sorted(g["vehicle_id"].unique(), key=lambda s: (len(s), s))
    arc = g.pivot(index="time_s", columns="vehicle_id", values="arc_pos_m")[ids]
    spd = g.pivot(index="time_s", columns="vehicle_id", values="speed_mps")[ids]
    return arc.index.to_numpy(), arc.to_numpy(), spd.to_numpy(), ids


def psi_for(gt: GroundTruth, sc: Scenario, run: int, time_s: float) -> np.ndarray:
    """Psi of the interval holding ``time_s``; bounds per the scenario's ``bounds_source``."""
    return psi_and_dispersion(gt, sc, run, time_s)[:6]


def psi_and_dispersion(gt: GroundTruth, sc: Scenario, run: int, time_s: float) -> np.ndarray:
    """Psi followed by the interval's spacing std [m] (7 values)."""
    m = gt.macro
    rows = m[
        (m["run"] == run)
        & (m["source"] == sc.generator.psi_source)
        & (m["begin_s"] <= time_s + 1e-9)
        & (m["end_s"] > time_s + 1e-9)
    ]
    if rows.empty:
        raise UserError(
            f"{gt.folder}/macro.csv: no {sc.generator.psi_source} row for run {run} at t = {time_s:g} s"
        )
    psi = rows.iloc[0][[*PSI_COLUMNS, "spacing_std_m"]].to_numpy(dtype=float)
    if sc.generator.bounds_source == "extended":
        n = float(rows.iloc[0]["n_samples"])
        for lo, hi in ((2, 3), (4, 5)):
            psi[lo], psi[hi] = extended_bounds(psi[lo], psi[hi], n)
    if sc.generator.bounds_source == "fixed":
        psi[2:4] = sc.bounds.spacing_m
        psi[4:6] = sc.bounds.speed_mps
    return psi


def snapshot_states(gt: GroundTruth, sc: Scenario, runs: np.ndarray) -> Snapshots:
    """Every ``snapshot_every_s`` of the given runs, inside complete detector intervals."""
    every = sc.generator.snapshot_every_s
    interval_end = gt.macro.groupby("run")["end_s"].max()
    out = {"run": [], "time_s": [], "arc": [], "speed": [], "psi": []}
    for run in runs:
        times, arc, spd, _ = run_arrays(gt.trajectories, run)
        pick = np.flatnonzero(np.abs(times / every - np.round(times / every)) < 1e-6)
        pick = pick[times[pick] < interval_end.get(run, 0.0) - 1e-9]
        for i in pick:
            out["run"].append(run)
            out["time_s"].append(times[i])
            out["arc"].append(arc[i])
            out["speed"].append(spd[i])
            out["psi"].append(psi_and_dispersion(gt, sc, run, times[i]))
    if not out["run"]:
        raise UserError(f"{gt.folder}: no snapshots in runs {list(runs)}")
    n = sc.fleet.n_vehicles
    return Snapshots(
        run=np.array(out["run"]),
        time_s=np.array(out["time_s"]),
        arc_m=np.array(out["arc"]),
        speed_mps=np.array(out["speed"]),
        psi=np.array(out["psi"])[:, :6],
        hidden=np.zeros((len(out["run"]), n), dtype=bool),
        length_m=sc.network.length_m,
        spacing_std_m=np.array(out["psi"])[:, 6]
        if sc.generator.spacing_dispersion == "measured"
        else None,
    )


def hide(states: Snapshots, k: np.ndarray | int, rng: np.random.Generator) -> Snapshots:
    """Mark ``k`` random vehicles of each snapshot hidden (``k`` scalar or per snapshot)."""
    b, n = states.arc_m.shape
    k = np.broadcast_to(np.asarray(k), (b,))
    if (k < 0).any() or (k > n).any():
        raise UserError(f"hidden count K must be in [0, {n}], got {sorted(set(k.tolist()))}")
    ranks = np.argsort(rng.random((b, n)), axis=1).argsort(axis=1)
    return replace(states, hidden=ranks < k[:, None])


def held_out_by_k(states: Snapshots, ks: range, seed: int) -> dict[int, Snapshots]:
    """The evaluation protocol: every held-out snapshot once per K, same seed per K."""
    return {k: hide(states, k, np.random.default_rng([seed, 11, k])) for k in ks}
