"""What the stages exchange on a section: the recorded truth, snapshots, psi, hidden counts.

Arrays are padded to the largest fleet in the set: ``valid`` says which slots hold a
vehicle. Positions are ``(lane index, arc)`` on the section (``section.Section``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.macro import extended_bounds, passage_spacings

# Re-exported: importable from here as before the split (truth.signals, env.section_bank).
from macromicro_sumo.data.section_signals import SIGNAL_COLUMNS as SIGNAL_COLUMNS
from macromicro_sumo.data.section_signals import signal_settings as signal_settings
from macromicro_sumo.data.section_signals import signal_stops
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import read_checked_csv
from macromicro_sumo.road.section import Section

# psi per snapshot, from the detectors' interval that holds it (columns of ``psi``):
PSI_FIELDS = (
    "mean_speed_mps",  # space-mean speed on the section
    "mean_spacing_m",  # 1 / density per lane
    "std_spacing_m",  # spread of the spacings (NaN where the detectors cannot tell)
    "speed_min_mps",  # admissible speeds [v_min, v_max]
    "speed_max_mps",
    "spacing_min_m",  # smallest admissible front-to-front spacing (length + min gap)
    "spacing_max_m",  # largest admissible spacing (inf unless generator.spacing_bounds)
    "spacing_low_m",  # shortest spacing to place at (spacing_min_m unless spacing_bounds)
)


# CPython's built-in SHA-256: hashlib's digest at 3.5 against 6.4 us an arrival (stop 46)
try:
    from _sha2 import sha256 as _SHA256  # Python 3.12+
except ImportError:  # Python 3.11; hashlib's where a build lacks the built-in
    try:
        from _sha256 import sha256 as _SHA256
    except ImportError:
        from hashlib import sha256 as _SHA256


def vehicle_level(seed: int, run: int, vehicle_id: str, tag: str = "") -> float:
    """A uniform level in [0, 1) per (seed, run, vehicle): a hash, not a generator, so a
    vehicle draws the same whatever drives it, in whatever order vehicles appear and however
    often its run is repeated; ``tag`` keeps the draws of different uses apart."""
    key = f"{tag}|{seed}|{run}|{vehicle_id}" if tag else f"{seed}|{run}|{vehicle_id}"
    return int.from_bytes(_SHA256(key.encode()).digest()[:8], "little") / 2**64


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
class SectionTruth:
    """A ground-truth folder of ``macromicro simulate`` on a section (see docs/sections.md)."""

    folder: Path
    section: Section
    trajectories: pd.DataFrame
    detectors: pd.DataFrame
    macro: pd.DataFrame
    vtypes: pd.DataFrame
    k_estimate: pd.DataFrame
    # signals.csv (``SIGNAL_COLUMNS``): the states of the signals on the section's links at
    # every recorded step; None: none recorded (no signal on the section, field data).
    signals: pd.DataFrame | None = None

    @property
    def runs(self) -> np.ndarray:
        return np.sort(self.trajectories["run"].unique())


@dataclass(frozen=True)
class SectionSnapshots:
    """Scenes on the section at snapshot times; (S, N) arrays padded with ``valid``."""

    run: np.ndarray  # (S,)
    time_s: np.ndarray  # (S,)
    lane: np.ndarray  # (S, N) int lane index
    arc_m: np.ndarray  # (S, N)
    speed_mps: np.ndarray  # (S, N)
    length_m: np.ndarray  # (S, N) vehicle lengths
    valid: np.ndarray  # (S, N) bool: a vehicle in this slot
    observed: np.ndarray  # (S, N) bool: instrumented (known to the method)
    psi: np.ndarray  # (S, len(PSI_FIELDS))
    k_true: np.ndarray  # (S,) hidden vehicles on the section (the simulation knows)
    k_est: np.ndarray  # (S,) hidden vehicles estimated from detector density
    # (S, P) the red or yellow stop lines on the section at the snapshot's time (lane index,
    # arc; NaN arc: none), standing leaders (``signal_stops``); None: no signal recorded.
    stop_lane: np.ndarray | None = None
    stop_arc_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.run)

    @property
    def hidden(self) -> np.ndarray:
        return self.valid & ~self.observed

    def take(self, idx: np.ndarray) -> SectionSnapshots:
        fields = self.__dataclass_fields__
        return SectionSnapshots(
            **{f: None if getattr(self, f) is None else getattr(self, f)[idx] for f in fields}
        )


def stop_lines_at(
    truth: SectionTruth, run: int, times_s: np.ndarray
) -> dict[float, tuple[np.ndarray, np.ndarray]]:
    """{time of run ``run`` (rounded to 1e-6 s): (lane, arc) of the red or yellow stop lines
    then} (``signal_stops``, the snapshots' and so the envs' standing leaders), at
    ``times_s``; empty: no signal recorded."""
    got = signal_stops(truth.signals, np.full(len(times_s), run), np.asarray(times_s))
    if got is None:
        return {}
    lane, arc = got
    ok = np.isfinite(arc)
    return {round(float(t), 6): (lane[i, ok[i]], arc[i, ok[i]]) for i, t in enumerate(times_s)}


def at_snapshot_times(traj: pd.DataFrame, every_s: float) -> pd.DataFrame:
    """The rows of ``traj`` at whole multiples of ``every_s`` (the snapshot grid)."""
    t = traj["time_s"].to_numpy()
    return traj[np.abs(t / every_s - np.round(t / every_s)) < 1e-6]


def psi_table(truth: SectionTruth, sc) -> pd.DataFrame:
    """psi per (run, interval) from the detectors, with bounds filled where they are silent.

    Speed bounds come from the passages of the interval, per ``generator.bounds_source``
    (the interval's extremes are a sample): "margin" widens them by 10%, "interval" keeps
    them, "extended" widens them by (max - min) / (n - 1), n the interval's passages (as
    the ring does); where there are none, [0, highest limit]. The smallest spacing is the
    shortest vehicle plus the scenario's minimum gap.
    """
    m = truth.macro[truth.macro["source"] == "detectors"].copy()
    # Each row's run's highest limit (drawn per run where the truth has speed_limits.csv).
    vmax_lim = np.nanmax(run_limits_mps(truth, m["run"].to_numpy()), axis=(1, 2))
    lo, hi = m["speed_min_mps"], m["speed_max_mps"]
    if sc.generator.bounds_source == "margin":
        lo, hi = lo * 0.9, hi * 1.1
    elif sc.generator.bounds_source == "extended":
        lo, hi = extended_bounds(lo, hi, interval_passages(truth, m))
    m["speed_min_mps"] = lo.fillna(0.0)
    hi = hi.to_numpy(dtype=float)
    m["speed_max_mps"] = np.minimum(np.where(np.isnan(hi), vmax_lim, hi), vmax_lim * 1.5)
    m["spacing_min_m"] = float(truth.vtypes["length_m"].min()) + psi_min_gap_m(truth, sc)
    m["spacing_max_m"] = np.inf
    m["spacing_low_m"] = m["spacing_min_m"]
    if sc.generator.spacing_bounds == "passages":
        low, high = spacing_bounds_m(truth, m, sc.generator.bounds_source)
        m["spacing_low_m"] = np.maximum(m["spacing_min_m"].to_numpy(), low)
        m["spacing_max_m"] = high
    return m


def psi_min_gap_m(truth: SectionTruth, sc) -> float:
    """The bumper gap [m] psi's smallest spacing adds to the shortest vType:
    ``bounds.min_gap_m``, or with ``bounds.psi_min_gap = "recorded"`` the recorded vTypes'
    smallest minGap where the truth records one (SUMO's drivers stand no closer)."""
    vt = truth.vtypes
    if sc.bounds.psi_min_gap == "recorded" and "min_gap_m" in vt and len(vt):
        return float(vt["min_gap_m"].min())
    return sc.bounds.min_gap_m


def interval_psi(psi: pd.DataFrame, run: int, time_s: float) -> np.ndarray | None:
    """psi (``PSI_FIELDS``) of the detector interval of ``psi`` (``psi_table``) that holds
    run ``run``'s time ``time_s``; None where none does or it measured no speed."""
    m = psi[(psi["run"] == run) & (psi["begin_s"] <= time_s) & (psi["end_s"] > time_s)]
    if m.empty or not np.isfinite(m["mean_speed_mps"].iloc[0]):
        return None
    return m.iloc[0][list(PSI_FIELDS)].to_numpy(dtype=float)


def spacing_bounds_m(truth: SectionTruth, m: pd.DataFrame, source: str) -> tuple[np.ndarray, ...]:
    """(rows of ``m``,) twice: psi's shortest and longest spacing [m] per interval, the ring's
    [d_min, d_max]: the extremes of the interval's passage spacings (headway x mean speed
    at each loop, the sample whose std is psi's ``std_spacing_m``), widened per
    ``generator.bounds_source`` as the speed bounds; (0, inf) where the interval has fewer
    than two spacings (no bound).

    Why: without it the completions' spacing spread has a long right tail (ring as a
    section, K = 3: scene variance / psi's 1.16 on average where the truth's is 0.97)."""
    path = truth.folder / "detector_passages.csv"
    if not path.is_file():
        raise UserError(
            f'{path}: missing; generator.spacing_bounds = "passages" reads the detectors\' '
            f'passages (field data has none: accepted "none")'
        )
    sp = passage_spacings(pd.read_csv(path, usecols=["run", "detector_id", "time_s", "speed_mps"]))
    # As truth.section_macro: a lane change between two loops is no spacing.
    sp = sp[sp["spacing_m"] >= 0.5 * float(m["spacing_min_m"].min())]
    by_run = {run: g for run, g in sp.groupby("run")}
    lo, hi, n = [], [], []
    for run, b, e in zip(m["run"], m["begin_s"], m["end_s"], strict=True):
        g = by_run.get(run)
        d = (
            np.array([])
            if g is None
            else g["spacing_m"].to_numpy()[
                (g["time_s"].to_numpy() >= b) & (g["time_s"].to_numpy() < e)
            ]
        )
        lo.append(d.min() if d.size > 1 else np.nan)
        hi.append(d.max() if d.size > 1 else np.nan)
        n.append(float(d.size))
    lo_a, hi_a, n_a = np.array(lo), np.array(hi), np.array(n)
    if source == "margin":
        lo_a, hi_a = lo_a * 0.9, hi_a * 1.1
    elif source == "extended":
        lo_a, hi_a = extended_bounds(lo_a, hi_a, n_a)
    return np.where(np.isnan(lo_a), 0.0, lo_a), np.where(np.isnan(hi_a), np.inf, hi_a)


LIMIT_COLUMNS = ("run", "edge_id", "speed_limit_mps")


def run_limits_mps(truth: SectionTruth, runs: np.ndarray) -> np.ndarray:
    """(len(runs), E, max lanes) each run's speed limits [m/s] (NaN: no lane): the truth's
    ``speed_limits.csv`` where it drew them per run (``[speed_limits]``: every lane of an
    edge takes the edge's limit), else the section's own (the network's) for every run."""
    runs = np.asarray(runs, dtype=np.int64)
    base = truth.section.limits_mps
    if not (truth.folder / "speed_limits.csv").is_file():
        return np.repeat(base[None], len(runs), axis=0)
    df = read_checked_csv(
        truth.folder,
        "speed_limits.csv",
        None,
        LIMIT_COLUMNS,
        ("run", "speed_limit_mps"),
        dtype={"edge_id": str},
    )
    table = df.pivot_table("speed_limit_mps", "run", "edge_id", aggfunc="first")
    edges = list(truth.section.edge_ids)
    no_edge = [e for e in edges if e not in table.columns]
    no_run = sorted(set(runs.tolist()) - set(table.index.tolist()))
    if no_edge or no_run:
        raise UserError(
            f"{truth.folder / 'speed_limits.csv'}: no limit for section edge(s) {no_edge} "
            f"or run(s) {no_run[:5]}; re-run `macromicro simulate`"
        )
    per_edge = table.loc[runs, edges].to_numpy(dtype=float)
    return np.where(np.isnan(base)[None], np.nan, per_edge[:, :, None])


def run_section(truth: SectionTruth, run: int) -> Section:
    """The truth's section with run ``run``'s speed limits (``run_limits_mps``)."""
    return dataclasses.replace(truth.section, limits_mps=run_limits_mps(truth, [run])[0])


def recorded_steps(run_frame: pd.DataFrame, dt_s: float) -> Iterator[tuple[pd.DataFrame, dict]]:
    """The steps of one run's trajectories: per recorded time t whose next recorded time is
    t + ``dt_s``, the rows at t and each vehicle's speed at t + dt (absent: gone). The one
    definition of a step the observed (observation, action) pairs are read over."""
    by_t = dict(tuple(run_frame.groupby("time_s")))
    times = np.sort(np.fromiter(by_t, float))
    for t0, t1 in zip(times[:-1], times[1:], strict=True):
        if abs(t1 - t0 - dt_s) <= 1e-6:
            nxt = by_t[t1]
            yield by_t[t0], dict(zip(nxt["vehicle_id"], nxt["speed_mps"], strict=True))


def interval_passages(truth: SectionTruth, m: pd.DataFrame) -> np.ndarray:
    """(rows of ``m``,) detector passages in each row's run and [begin_s, end_s): the
    sample whose extremes are the interval's speed bounds (``truth.section_macro``)."""
    path = truth.folder / "detector_passages.csv"
    if not path.is_file():
        raise UserError(
            f'{path}: missing; generator.bounds_source = "extended" counts each interval\'s '
            f'passages (field data has none: accepted "margin" or "interval")'
        )
    p = pd.read_csv(path, usecols=["run", "time_s"])
    times = {run: np.sort(g.to_numpy()) for run, g in p.groupby("run")["time_s"]}
    none = np.array([])
    return np.array(
        [
            np.searchsorted(t, e, side="left") - np.searchsorted(t, b, side="left")
            for run, b, e in zip(m["run"], m["begin_s"], m["end_s"], strict=True)
            for t in (times.get(run, none),)
        ],
        dtype=np.float64,
    )


def section_snapshots(
    truth: SectionTruth, sc, runs: np.ndarray, k_range: tuple[int, int] | None = None
) -> SectionSnapshots:
    """Scenes every ``generator.snapshot_every_s`` of ``runs`` with psi and hidden counts.

    Observed: the instrumented vehicles (``instrumented.hidden = "run"``), or with
    ``"snapshot"`` K random vehicles of each scene hidden, K drawn per snapshot from
    ``k_range`` (default ``policy.hidden_train``: Stage II's episodes) by ``hide_random``,
    seeded by the scenario's seed."""
    snaps = recorded_snapshots(truth, sc, runs)
    if not hidden_per_snapshot(sc):
        return snaps
    rng = np.random.default_rng([sc.seed, HIDDEN_STREAM])
    return hide_random(snaps, draw_k(snaps, k_range or sc.policy.hidden_train, rng), rng)


def hidden_per_snapshot(sc) -> bool:
    """Whether the scenario draws its hidden sets per snapshot (``instrumented.hidden``)."""
    return sc.instrumented.hidden == "snapshot"


# The seed stream of the hidden sets (numpy SeedSequence [seed, stream, ...]); the ring's
# streams are 1, 2 (generator), 7 (splits) and 11 (evaluation).
HIDDEN_STREAM = 43


def draw_k(
    snaps: SectionSnapshots, k_range: tuple[int, int], rng: np.random.Generator
) -> np.ndarray:
    """(S,) hidden counts drawn uniformly from ``k_range`` (inclusive), each at most its
    snapshot's vehicles."""
    lo, hi = k_range
    return np.minimum(rng.integers(lo, hi + 1, len(snaps)), snaps.valid.sum(axis=1))


def hide_random(
    snaps: SectionSnapshots, k: np.ndarray | int, rng: np.random.Generator
) -> SectionSnapshots:
    """``snaps`` with ``k`` random vehicles of each scene hidden (scalar or per snapshot),
    every other vehicle observed (the paper's protocol) on padded scenes.

    ``k_true`` becomes ``k``; ``k_est`` the detectors' vehicle count (``k_est`` plus the
    observed vehicles before) minus the observed ones now."""
    s_n, n = snaps.valid.shape
    k = np.broadcast_to(np.asarray(k, dtype=np.int64), (s_n,))
    counts = snaps.valid.sum(axis=1)
    if (k < 0).any() or (k > counts).any():
        i = int(np.flatnonzero((k < 0) | (k > counts))[0])
        raise UserError(
            f"run {snaps.run[i]}, t = {snaps.time_s[i]:g} s: cannot hide {k[i]} of its "
            f"{counts[i]} vehicles; accepted 0..{counts[i]}"
        )
    # Random ranks among the valid slots (padding ranks last): the k lowest are hidden.
    keys = np.where(snaps.valid, rng.random((s_n, n)), np.inf)
    ranks = np.argsort(np.argsort(keys, axis=1), axis=1)
    hidden = snaps.valid & (ranks < k[:, None])
    observed = snaps.valid & ~hidden
    vehicles_est = snaps.k_est + snaps.observed.sum(axis=1)
    return dataclasses.replace(
        snaps,
        observed=observed,
        k_true=k.copy(),
        k_est=np.maximum(0, vehicles_est - observed.sum(axis=1)),
    )


def snapshots_by_k(snaps: SectionSnapshots, ks: range, seed: int) -> dict[int, SectionSnapshots]:
    """The evaluation protocol of ``instrumented.hidden = "snapshot"``: every snapshot with
    at least K vehicles once per K, its hidden set drawn afresh (seed per K)."""
    out = {}
    for k in ks:
        idx = np.flatnonzero(snaps.valid.sum(axis=1) >= k)
        if idx.size:
            out[k] = hide_random(
                snaps.take(idx), k, np.random.default_rng([seed, HIDDEN_STREAM, k])
            )
    return out


def concat_snapshots(parts: list[SectionSnapshots]) -> SectionSnapshots:
    """The snapshots of ``parts`` one after the other (the same padding: one recorded set)."""
    fields = SectionSnapshots.__dataclass_fields__
    out = {}
    for f in fields:
        got = [getattr(p, f) for p in parts]
        if any(x is None for x in got):  # stop lines: all parts' or none
            out[f] = None
            continue
        if f.startswith("stop_"):  # padded to the widest part's count
            w = max(x.shape[1] for x in got)
            pad = np.nan if f == "stop_arc_m" else 0
            got = [np.pad(x, ((0, 0), (0, w - x.shape[1])), constant_values=pad) for x in got]
        out[f] = np.concatenate(got)
    return SectionSnapshots(**out)


def recorded_snapshots(truth: SectionTruth, sc, runs: np.ndarray) -> SectionSnapshots:
    """The scenes with the truth's instrumented vehicles observed, whatever
    ``instrumented.hidden`` says (``section_snapshots`` draws the hidden sets on them)."""
    every = sc.generator.snapshot_every_s
    traj = truth.trajectories
    traj = traj[traj["run"].isin(runs)]
    traj = at_snapshot_times(traj, every)
    psi = psi_table(truth, sc)
    k = truth.k_estimate.set_index(["run", "time_s"])
    lengths = dict(zip(truth.vtypes["vtype"], truth.vtypes["length_m"], strict=True))
    scenes = []
    for (run, time_s), g in traj.groupby(["run", "time_s"], sort=True):
        p = interval_psi(psi, run, time_s)
        if p is not None and (run, time_s) in k.index:
            scenes.append((run, time_s, g, p))
    if not scenes:
        raise UserError(
            f"{truth.folder}: no snapshot of runs {list(runs)} falls in a detector interval"
        )
    s_n, n = len(scenes), max(len(g) for _, _, g, _ in scenes)
    lane = np.zeros((s_n, n), dtype=np.int64)
    arc, speed, length = np.zeros((s_n, n)), np.zeros((s_n, n)), np.zeros((s_n, n))
    valid, observed = np.zeros((s_n, n), bool), np.zeros((s_n, n), bool)
    for i, (_, _, g, _) in enumerate(scenes):
        j = len(g)
        lane[i, :j] = g["lane_index"].to_numpy()
        arc[i, :j] = g["arc_m"].to_numpy()
        speed[i, :j] = g["speed_mps"].to_numpy()
        length[i, :j] = g["vtype"].map(lengths).to_numpy(dtype=float)
        valid[i, :j] = True
        observed[i, :j] = g["observed"].to_numpy(dtype=bool)
    keys = [(r, t) for r, t, _, _ in scenes]
    run_ids, times = np.array([r for r, _ in keys]), np.array([t for _, t in keys])
    stops = signal_stops(truth.signals, run_ids, times) or (None, None)
    return SectionSnapshots(
        run=run_ids,
        time_s=times,
        lane=lane,
        arc_m=arc,
        speed_mps=speed,
        length_m=length,
        valid=valid,
        observed=observed,
        psi=np.stack([p for *_, p in scenes]),
        k_true=k.loc[keys, "k_true"].to_numpy(),
        k_est=k.loc[keys, "k_est"].to_numpy(),
        stop_lane=stops[0],
        stop_arc_m=stops[1],
    )
