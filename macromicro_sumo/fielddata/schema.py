"""The two frames every field-data reader produces, units, and the one-line input errors.

Readers hand the rest of the pipeline exactly the tables ``macromicro simulate`` writes
(docs/sections.md): observed trajectories in the ``trajectories.csv`` schema and station
data in the ``detectors.csv`` schema, so later stages cannot tell field data from a
simulated ground truth. Every problem in a file is a ``UserError`` naming the file, the
row (and the line an editor shows) and the column, with the accepted range or unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError

TRAJ_COLUMNS = (
    "run",
    "time_s",
    "vehicle_id",
    "vtype",
    "observed",
    "lane_index",
    "edge_index",
    "arc_m",
    "speed_mps",
    "accel_mps2",
)
# The observed vehicle's own measurement of its leader (radar; NGSIM Preceding /
# Space_Headway, highD precedingId / dhw / precedingXVelocity): optional columns after
# TRAJ_COLUMNS, present when the layout carries them. ``leader_id`` "" and the other two
# NaN: no vehicle ahead was measured in that row.
LEADER_COLUMNS = ("leader_id", "leader_spacing_m", "leader_speed_mps")
DET_COLUMNS = (
    "run",
    "detector_id",
    "kind",
    "source",
    "lane_index",
    "arc_m",
    "begin_s",
    "end_s",
    "n_veh",
    "flow_vph",
    "speed_mps",
    "occupancy_pct",
    "density_vpkm",
    "length_m",
)

# Faster than any road vehicle: a speed above it is a unit declared wrong (ft/s read as m/s).
MAX_SPEED_MPS = 100.0


def where(path: Path | str, row: int | None, column: str, line: int | None = None) -> str:
    """``file: row R (line L), column 'C'``; ``row`` is the 0-based data record (a CSV with a
    header: line = row + 2; XML: ``line`` from the parser), None: the whole column."""
    if row is None:
        return f"{path}: column {column!r}"
    return f"{path}: row {row + 1} (line {row + 2 if line is None else line}), column {column!r}"


def require_columns(df: pd.DataFrame, columns: list[str] | tuple[str, ...], path: Path) -> None:
    """Every column a layout needs is there; else one line naming the first missing one."""
    for col in columns:
        if col not in df.columns:
            have = ", ".join(map(str, df.columns[:12]))
            raise UserError(
                f"{where(path, None, col)}: missing; the file has {have}"
                f"{', ...' if len(df.columns) > 12 else ''}"
            )


def numbers(df: pd.DataFrame, column: str, path: Path, allow_nan: bool = False) -> np.ndarray:
    """A column as floats; the first entry that is not a finite number is a one-line error
    (empty cells are NaN where ``allow_nan``: a loop with no vehicle has no speed)."""
    raw = df[column]
    values = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if allow_nan:
        bad &= raw.notna().to_numpy() & (raw.astype(str).str.strip() != "").to_numpy()
    hit = np.flatnonzero(bad)
    if hit.size:
        i = int(hit[0])
        # The frame's index labels are the file's data rows (subsets keep them).
        row = int(df.index[i]) if pd.api.types.is_integer_dtype(df.index) else i
        raise UserError(
            f"{where(path, row, column)}: {raw.iloc[i]!r} is not a finite number"
            + ("" if allow_nan else " (no empty cells)")
        )
    return values


def check_range(
    values: np.ndarray,
    lo: float,
    hi: float,
    path: Path,
    column: str,
    what: str,
    hint: str = "",
    rows: np.ndarray | None = None,
    lines: np.ndarray | None = None,
) -> None:
    """Values outside [lo, hi] (NaN passes): one line naming the first, with the range in
    SI units and a ``hint`` (which unit setting to check). ``rows``/``lines``: where in the
    file each value stands (default: CSV data rows in order)."""
    with np.errstate(invalid="ignore"):
        hit = np.flatnonzero((values < lo) | (values > hi))
    if hit.size:
        i = int(hit[0])
        row = int(rows[i]) if rows is not None else i
        line = int(lines[i]) if lines is not None else None
        raise UserError(
            f"{where(path, row, column, line)}: {what} {values[i]:.6g} is outside the accepted "
            f"[{lo:g}, {hi:g}]{'; ' + hint if hint else ''}"
        )


def unit(table: dict[str, float], name: str, key: str, source: str) -> float:
    """The SI factor of a declared unit; an unknown unit is a one-line error."""
    if name not in table:
        raise UserError(
            f"{source}: {key} = {name!r} is not a known unit; accepted: {', '.join(table)}"
        )
    return table[name]


def read_table(path: Path | str, **kwargs: object) -> pd.DataFrame:
    """A CSV (or whitespace table) as strings-or-numbers; unreadable files are one line."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: missing")
    try:
        df = pd.read_csv(path, **kwargs)  # type: ignore[arg-type]
    except (ValueError, OSError) as exc:  # pandas' parser and decoding errors are ValueErrors
        raise UserError(f"{path}: not a readable CSV ({type(exc).__name__}: {exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    if df.empty:
        raise UserError(f"{path}: no data rows")
    return df
