"""Stage I alone: ``macromicro complete``, partly observed scenes completed by a trained
generator and written as CSV.

The scenes are the ground truth's held-out snapshots (as the evaluation completes them),
one snapshot of the ground truth (``--snapshot RUN:TIME``) or a CSV of the vehicles a user
observed (``--snapshot FILE.csv``, ``SNAPSHOT_COLUMNS``). psi, the detectors' statistics
the generator completes against, is the ground truth's detector interval that holds each
scene's time; a user's scene hides the vehicles the detectors estimate on the section
minus the ones it lists, or ``--hidden K``. Each scene is completed ``completions`` times,
completion c seeded ``seed + c`` (same seed, same bytes). Columns: docs/sections.md,
"Completing scenes".
"""

from __future__ import annotations

import math
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.data.hidden_counts import scenes_hiding
from macromicro_sumo.data.section import (
    SectionSnapshots,
    SectionTruth,
    concat_snapshots,
    hidden_per_snapshot,
    interval_psi,
    psi_table,
    recorded_snapshots,
    snapshots_by_k,
    split_runs,
)
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import (
    prepare_out_dir,
    staging_dir,
    write_csv,
    write_stage_manifest,
    writer_session,
)
from macromicro_sumo.generator.section_metrics import completion_metrics
from macromicro_sumo.generator.section_sampler import (
    SectionCompletion,
    complete_section,
    generated_length,
    k_of,
)
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.road.section import Section
from macromicro_sumo.truth.section import load_section_truth

MANIFEST = "complete_manifest.json"
# A user's observed vehicles: every row one vehicle of the scene at (run, time_s); a
# position is (lane_index, arc_m) on the section or (edge_id, lane_index, pos_m) on SUMO's lane.
SNAPSHOT_COLUMNS = ("run", "time_s", "lane_index", "speed_mps")
COMPLETION_COLUMNS = (
    "completion",
    "scene",
    "run",
    "time_s",
    "k_generated",  # vehicles the generator placed in this scene
    "k_true",  # vehicles the scene hides (the simulation's count; -1: unknown)
    "vehicle",
    "role",  # observed | generated
    "edge_id",
    "lane_index",
    "pos_m",  # position on the edge's lane, as SUMO counts it
    "arc_m",  # position along the section
    "speed_mps",
)
MAX_COMPLETIONS = 100
_RUN_TIME = re.compile(r"^(\d+):(\d+(?:\.\d*)?)$")


# --------------------------------------------------------------------------- the scenes


def truth_scenes(
    sc, truth: SectionTruth, snapshot: str | None, hidden: list[int] | None
) -> tuple[SectionSnapshots, str]:
    """The ground truth's scenes to complete and a label of where they come from: the
    held-out snapshots, or one snapshot ``RUN:TIME`` of any run. ``hidden`` keeps the scenes
    hiding those K (``scenes_hiding``); without it a ring-like scenario (``instrumented.hidden
    = "snapshot"``) hides each K of ``generator.hidden_eval`` in turn (the evaluation's
    scenes) and a section keeps its instrumented vehicles' scenes as they are."""
    if snapshot is None:
        held = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)["held_out"]
        scenes = recorded_snapshots(truth, sc, held)
        where = f"the held-out runs {held.tolist()} of {truth.folder}"
    else:
        run, time_s = _run_time(snapshot, truth)
        scenes = recorded_snapshots(truth, sc, np.array([run]))
        scenes = scenes.take(np.flatnonzero(np.isclose(scenes.time_s, time_s)))
        if not len(scenes):
            raise UserError(
                f"--snapshot {snapshot}: {truth.folder} has no snapshot of run {run} at "
                f"t = {time_s:g} s inside a detector interval; accepted: multiples of "
                f"generator.snapshot_every_s = {sc.generator.snapshot_every_s:g} s"
            )
        where = f"snapshot {snapshot} of {truth.folder}"
    if hidden:
        return scenes_hiding(sc, scenes, hidden, where)[0], where
    if hidden_per_snapshot(sc):
        lo, hi = sc.generator.hidden_eval
        parts = list(snapshots_by_k(scenes, range(lo, hi + 1), sc.seed).values())
        if not parts:
            raise UserError(
                f"{where}: no snapshot holds {lo} vehicles to hide "
                f"(generator.hidden_eval = [{lo}, {hi}]); pass --hidden K"
            )
        return concat_snapshots(parts), where
    return scenes, where


def _run_time(snapshot: str, truth: SectionTruth) -> tuple[int, float]:
    m = _RUN_TIME.match(snapshot)
    if m is None:
        raise UserError(
            f"--snapshot {snapshot}: not a CSV file nor RUN:TIME; accepted: a CSV of observed "
            "vehicles or a ground-truth snapshot such as 0:60"
        )
    run, time_s = int(m.group(1)), float(m.group(2))
    if run not in truth.runs:
        raise UserError(
            f"--snapshot {snapshot}: {truth.folder} has no run {run}; accepted runs "
            f"{int(truth.runs.min())}..{int(truth.runs.max())}"
        )
    return run, time_s


def user_scenes(
    sc, truth: SectionTruth, path: Path, hidden: list[int] | None
) -> tuple[SectionSnapshots, np.ndarray]:
    """A user's CSV of observed vehicles as scenes (one per (run, time_s)) and the hidden
    count of each: ``hidden`` (each K once per scene) or the detectors' estimate of the
    vehicles on the section at that time minus the scene's observed ones."""
    df = _read_snapshot_csv(path, truth.section)
    psi = psi_table(truth, sc)
    # the detectors' vehicles on the section per snapshot (the truth's hidden + observed)
    k_df = truth.k_estimate
    vehicles = {
        (int(r), round(float(t), 6)): int(k) + int(o)
        for r, t, k, o in zip(
            k_df["run"], k_df["time_s"], k_df["k_est"], k_df["n_observed"], strict=True
        )
    }
    lengths = dict(zip(truth.vtypes["vtype"], truth.vtypes["length_m"], strict=True))
    typical = float(np.median(truth.vtypes["length_m"]))
    groups = list(df.groupby(["run", "time_s"], sort=True))
    n = max(len(g) for _, g in groups)
    s_n = len(groups)
    lane, arc = np.zeros((s_n, n), np.int64), np.zeros((s_n, n))
    speed, length = np.zeros((s_n, n)), np.zeros((s_n, n))
    valid, psi_rows, k_est = np.zeros((s_n, n), bool), [], []
    for i, ((run, time_s), g) in enumerate(groups):
        row = interval_psi(psi, run, time_s)
        if row is None:
            raise UserError(
                f"{path}: run {run}, time_s {time_s:g}: no detector interval of {truth.folder} "
                f"with a measured speed holds it; accepted: the ground truth's runs "
                f"{truth.runs.tolist()} and times inside their detector intervals"
            )
        psi_rows.append(row)
        j = len(g)
        lane[i, :j], arc[i, :j] = g["lane_index"], g["arc_m"]
        speed[i, :j], valid[i, :j] = g["speed_mps"], True
        # a length given, else the vType's, else the truth's typical vehicle
        by_type = g["vtype"].map(lengths) if "vtype" in g else pd.Series(np.nan, g.index)
        length[i, :j] = g.get("length_m", by_type).fillna(by_type).fillna(typical)
        seen = vehicles.get((int(run), round(float(time_s), 6)))
        k_est.append(-1 if seen is None else max(0, seen - j))  # less the ones the user saw
    scenes = SectionSnapshots(
        run=np.array([r for (r, _), _ in groups], dtype=np.int64),
        time_s=np.array([t for (_, t), _ in groups], dtype=float),
        lane=lane,
        arc_m=arc,
        speed_mps=speed,
        length_m=length,
        valid=valid,
        observed=valid.copy(),
        psi=np.stack(psi_rows),
        k_true=np.full(s_n, -1, dtype=np.int64),  # nobody counted a user's scene
        k_est=np.array(k_est, dtype=np.int64),
    )
    if hidden:
        ks = np.repeat(np.asarray(hidden, dtype=np.int64)[None], s_n, axis=0).T.ravel()
        idx = np.tile(np.arange(s_n), len(hidden))
        return scenes.take(idx), ks
    missing = np.flatnonzero(scenes.k_est < 0)
    if missing.size:
        i = int(missing[0])
        raise UserError(
            f"{path}: run {scenes.run[i]}, time_s {scenes.time_s[i]:g} is no snapshot time of "
            f"{truth.folder / 'k_estimate.csv'}, so the detectors' vehicle count is unknown; "
            f"pass --hidden K or use multiples of generator.snapshot_every_s = "
            f"{sc.generator.snapshot_every_s:g} s"
        )
    return scenes, scenes.k_est.copy()


def _read_snapshot_csv(path: Path, section: Section) -> pd.DataFrame:
    """The user's CSV, checked: columns, finite numbers, lanes and positions on the section
    (every problem one line naming the file, the column and the line)."""
    try:
        df = pd.read_csv(path, dtype={"edge_id": str, "vehicle_id": str, "vtype": str})
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable CSV ({type(exc).__name__}: {exc})") from None
    missing = [c for c in SNAPSHOT_COLUMNS if c not in df.columns]
    if "arc_m" not in df and not {"edge_id", "pos_m"} <= set(df.columns):
        missing.append("arc_m (or edge_id + pos_m)")
    if missing:
        raise UserError(
            f"{path}: missing column(s) {', '.join(missing)}; accepted: "
            f"{', '.join(SNAPSHOT_COLUMNS)} and arc_m or edge_id + pos_m (optional length_m, "
            "vtype, vehicle_id)"
        )
    if df.empty:
        raise UserError(f"{path}: no vehicle rows; accepted: one row per observed vehicle")
    numeric = [c for c in (*SNAPSHOT_COLUMNS, "arc_m", "pos_m", "length_m") if c in df]
    for col in numeric:
        values = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise UserError(
                f"{path}: column {col}, line {bad[0] + 2}: {df[col].iloc[bad[0]]!r} is not a "
                "finite number; accepted: finite numbers"
            )
        df[col] = values
    _check_range(path, df, "run", 0, math.inf, integer=True)
    _check_range(path, df, "time_s", 0, math.inf)
    _check_range(path, df, "speed_mps", 0, 100)
    _check_range(path, df, "lane_index", 0, section.max_lanes - 1, integer=True)
    if "length_m" in df:
        _check_range(path, df, "length_m", 0.1, 30)
    df["run"], df["lane_index"] = df["run"].astype(np.int64), df["lane_index"].astype(np.int64)
    if "arc_m" not in df:  # SUMO's lane positions onto the section
        arcs = []
        for i, (edge, lane, pos) in enumerate(
            zip(df["edge_id"], df["lane_index"], df["pos_m"], strict=True)
        ):
            hit = section.locate(f"{edge}_{lane}", float(pos))
            if hit is None:
                raise UserError(
                    f"{path}: line {i + 2}: lane {edge}_{lane} is not a lane of the section; "
                    f"accepted edges {list(section.edge_ids)} and their lanes"
                )
            arcs.append(hit[1])
        df["arc_m"] = arcs
    hi = section.length_m if section.closed else section.lane_length_m
    _check_range(path, df, "arc_m", 0, hi, right_open=section.closed)
    return df


def _check_range(
    path: Path,
    df: pd.DataFrame,
    col: str,
    lo: float,
    hi: float,
    integer: bool = False,
    right_open: bool = False,
) -> None:
    v = df[col].to_numpy(dtype=float)
    bad = (v < lo) | (v >= hi if right_open else v > hi)
    if integer:
        bad |= v != np.round(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        kind = "whole numbers " if integer else ""
        shown = f"{hi:g}" if math.isfinite(hi) else "inf"
        raise UserError(
            f"{path}: column {col}, line {i + 2}: {df[col].iloc[i]!r}; accepted {kind}in "
            f"[{lo:g}, {shown}{')' if right_open else ']'}"
        )


# --------------------------------------------------------------------------- the tables


def completions_frame(
    section: Section,
    scenes: SectionSnapshots,
    comps: list[SectionCompletion],
    k: np.ndarray,
) -> pd.DataFrame:
    """completions.csv: every vehicle of every completed scene, ``COMPLETION_COLUMNS``."""
    frames = []
    for c, comp in enumerate(comps):
        s_idx, slot = np.nonzero(comp.valid)
        df = _vehicles(section, scenes, s_idx, slot, comp.lane, comp.arc_m, comp.speed_mps)
        df["completion"], df["k_generated"] = c, k[s_idx]
        df["role"] = np.where(comp.generated[s_idx, slot], "generated", "observed")
        frames.append(df)
    out = pd.concat(frames, ignore_index=True)
    return out[list(COMPLETION_COLUMNS)]


def hidden_truth_frame(section: Section, scenes: SectionSnapshots) -> pd.DataFrame:
    """hidden_truth.csv: the recorded states of the vehicles each scene hides."""
    s_idx, slot = np.nonzero(scenes.hidden)
    df = _vehicles(section, scenes, s_idx, slot, scenes.lane, scenes.arc_m, scenes.speed_mps)
    return df.drop(columns="k_true")


def _vehicles(section, scenes, s_idx, slot, lane, arc, speed) -> pd.DataFrame:
    where = [
        section.to_lane(int(la), float(a))
        for la, a in zip(lane[s_idx, slot], arc[s_idx, slot], strict=True)
    ]
    return pd.DataFrame(
        {
            "scene": s_idx,
            "run": scenes.run[s_idx],
            "time_s": scenes.time_s[s_idx],
            "k_true": scenes.k_true[s_idx],
            "vehicle": slot,
            "edge_id": [section.edge_ids[e] for e, _, _ in where],
            "lane_index": lane[s_idx, slot],
            "pos_m": [p for _, _, p in where],
            "arc_m": arc[s_idx, slot],
            "speed_mps": speed[s_idx, slot],
        }
    )


# --------------------------------------------------------------------------- the stage


def run_complete(
    sc,
    generator: Path,
    data: Path,
    out: Path,
    snapshot: str | None = None,
    hidden: list[int] | None = None,
    completions: int = 1,
    seed: int | None = None,
    command: str = "",
) -> dict[str, Any]:
    """The ``complete`` command: completions.csv (and from the ground truth's own scenes
    hidden_truth.csv and completion_metrics.csv) and complete_manifest.json in ``out``."""
    if not 1 <= completions <= MAX_COMPLETIONS:
        raise UserError(f"--completions {completions}: accepted 1..{MAX_COMPLETIONS}")
    if any(k < 0 for k in hidden or ()):
        raise UserError(f"--hidden {min(hidden or [0])}: accepted K >= 0")
    seed = sc.seed if seed is None else seed
    if not 0 <= seed < 2**32:
        raise UserError(f"--seed {seed}: accepted 0..{2**32 - 1}")
    truth = load_section_truth(Path(data), sc)
    net = load_section_generator(generator, sc)
    user = snapshot is not None and Path(snapshot).suffix.lower() == ".csv"
    if user:
        path = Path(snapshot)
        if not path.is_file():
            raise UserError(f"--snapshot {path}: no such file; accepted a CSV of observed vehicles")
        scenes, k = user_scenes(sc, truth, path, hidden)
        where = str(path)
    else:
        scenes, where = truth_scenes(sc, truth, snapshot, hidden)
        k = k_of(scenes, sc.generator.k_source)
    with writer_session():
        out = prepare_out_dir(out, [data, generator, *([snapshot] if user else [])])
        t0 = time.perf_counter()
        comps = [
            complete_section(
                net,
                truth.section,
                scenes,
                k,
                sc.generator.t_max,
                seed + c,
                -sc.bounds.accel_mps2[0],
                sc.simulation.step_length_s,
                generated_length(truth),  # Stage II's generated vehicles'
            )
            for c in range(completions)
        ]
        wall_s = time.perf_counter() - t0
        with staging_dir(out) as stage:
            files = ["completions.csv"]
            write_csv(completions_frame(truth.section, scenes, comps, k), stage / files[0])
            if not user:
                write_csv(hidden_truth_frame(truth.section, scenes), stage / "hidden_truth.csv")
                metrics = []
                for c, comp in enumerate(comps):
                    m = completion_metrics(truth.section, scenes, comp, k)
                    m.insert(0, "scene", np.arange(len(scenes)))
                    m.insert(0, "completion", c)
                    metrics.append(m)
                write_csv(pd.concat(metrics, ignore_index=True), stage / "completion_metrics.csv")
                files += ["hidden_truth.csv", "completion_metrics.csv"]
            manifest = build_manifest(sc, command, stage="complete")
            manifest.update(
                ground_truth=str(data),
                generator=str(generator),
                scenes_from=where,
                scenes=len(scenes),
                completions=completions,
                completion_seeds=[seed + c for c in range(completions)],
                hidden_counts=sorted({int(x) for x in k}),
                projections=int(sum(int(c.projections.sum()) for c in comps)),
                dropped=int(sum(0 if c.dropped is None else int(c.dropped.sum()) for c in comps)),
                timings_s={"complete": round(wall_s, 3)},
            )
            write_stage_manifest(manifest, stage, MANIFEST, files)
    return manifest
