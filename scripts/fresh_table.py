"""A fresh network's figures for docs/deploy-log.md in one go: the table of every method that
``scripts/deploy_runs.py`` deployed (speed RMSE and bias, per run, density RMSE, GEH < 5,
speed within 5%, collisions, teleports, emergency brakings), the truth against itself
(``scripts/truth_floor.py --out``), and where one method loses to another by station
(``--versus A B``: each station's speed RMSE of both and its share of the pooled MSE gap,
n x (MSE A - MSE B), largest first). Several ``--out`` folders of one run may be given
(the policy in one, the baselines in another); a method deployed twice is refused.

    .venv/bin/python scripts/fresh_table.py DR1901 DR1901b [--floor floor1901.csv] \\
        [--versus policy sumo_default] [--top 8]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.deploy.stations import ALL_LANES

ORDER = ("policy", "sumo_default", "idm_calibrated", "idm_detectors", "oracle_population", "oracle")
SAFETY = ("collisions", "teleports", "emergency_brakings")
HEADER = (
    "| method | speed RMSE m/s (bias) | per run | density RMSE veh/km | GEH < 5 | within 5% "
    "| collisions | teleports | emergency brakings |\n|---|---|---|---|---|---|---|---|---|"
)


def read_folders(folders: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(deploy_summary, deploy_runs, deploy_comparison) of ``folders`` stacked; a method
    found in two folders is an error (which of them would the table show?)."""
    parts: dict[str, list[pd.DataFrame]] = {"summary": [], "runs": [], "comparison": []}
    for f in folders:
        for key in parts:
            path = f / f"deploy_{key}.csv"
            if not path.is_file():
                raise SystemExit(f"fresh_table.py: {path} not found (a deploy_runs.py --out)")
            parts[key].append(pd.read_csv(path))
    summary = pd.concat(parts["summary"], ignore_index=True)
    twice = summary["method"][summary["method"].duplicated()].tolist()
    if twice:
        raise SystemExit(f"fresh_table.py: {twice} deployed in more than one folder")
    return summary, *(pd.concat(parts[k], ignore_index=True) for k in ("runs", "comparison"))


def _count(v: float) -> str:
    return "n/a" if pd.isna(v) else f"{int(v)}"


def method_rows(summary: pd.DataFrame, runs: pd.DataFrame) -> list[str]:
    """One markdown row per method, in ORDER (others after, as found)."""
    known = [m for m in ORDER if m in set(summary["method"])]
    rest = [m for m in summary["method"] if m not in ORDER]
    rows = []
    for m in known + rest:
        s = summary[summary["method"] == m].iloc[0]
        per = runs[runs["method"] == m].sort_values("run")["speed_rmse_mps"]
        rows.append(
            f"| `{m}` | {s.speed_rmse_mps:.3f} ({s.speed_bias_mps:+.2f}) | "
            + " / ".join(f"{v:.3f}" for v in per)
            + f" | {s.density_rmse_vpkm:.2f} | {100 * s.share_geh_below_5:.1f}% | "
            f"{100 * s.share_speed_within_5pct:.1f}% | "
            + " | ".join(_count(s.get(c, np.nan)) for c in SAFETY)
            + " |"
        )
    return rows


def floor_row(path: Path) -> str:
    """The truth against itself: ``truth_floor.py --out``'s pooled row ("all")."""
    f = pd.read_csv(path)
    a = f[f["pair"].astype(str) == "all"].iloc[0]
    return (
        f"| truth against truth | {a.speed_rmse_mps:.3f} ({a.speed_bias_mps:+.2f}) | | "
        f"{a.density_rmse_vpkm:.2f} | {100 * a.share_geh_below_5:.1f}% | "
        f"{100 * a.share_speed_within_5pct:.1f}% | | | |"
    )


def station_gap(comparison: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per station (lanes pooled, intervals with both speeds on both methods): the speed
    RMSE and bias of ``a`` and ``b`` and ``gap`` = n x (MSE a - MSE b), whose sum over the
    stations is the pooled n x MSE difference (what decides which method wins)."""
    s = comparison[comparison["lane"] == ALL_LANES].copy()
    s["err"] = s["speed_method_mps"] - s["speed_truth_mps"]
    keys = ["run", "station", "begin_s"]
    both = s[s["method"] == a].merge(s[s["method"] == b], on=keys, suffixes=("_a", "_b"))
    both = both.dropna(subset=["err_a", "err_b"])
    g = both.groupby("station")
    out = pd.DataFrame(
        {
            "arc_m": g["arc_m_a"].first(),
            "n": g.size(),
            f"rmse_{a}": g["err_a"].apply(lambda e: float(np.sqrt(np.mean(e**2)))),
            f"rmse_{b}": g["err_b"].apply(lambda e: float(np.sqrt(np.mean(e**2)))),
            f"bias_{a}": g["err_a"].mean(),
            f"bias_{b}": g["err_b"].mean(),
            "truth_v": g["speed_truth_mps_a"].mean(),
        }
    )
    out["gap"] = out["n"] * (out[f"rmse_{a}"] ** 2 - out[f"rmse_{b}"] ** 2)
    return out.sort_values("gap", ascending=False)


def get_options(args: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", type=Path, nargs="+", help="scripts/deploy_runs.py --out folders")
    p.add_argument("--floor", type=Path, default=None, help="scripts/truth_floor.py --out CSV")
    p.add_argument("--versus", nargs=2, default=None, metavar=("A", "B"), help="station gaps")
    p.add_argument("--top", type=int, default=8, help="stations shown by --versus")
    return p.parse_args(args)


def main(args: list[str] | None = None) -> int:
    o = get_options(args)
    summary, runs, comparison = read_folders(o.folders)
    print(HEADER)
    print("\n".join(method_rows(summary, runs)))
    if o.floor is not None:
        print(floor_row(o.floor))
    if o.versus:
        a, b = o.versus
        gaps = station_gap(comparison, a, b)
        print(f"\nstations by n x (MSE {a} - MSE {b}); sum {gaps['gap'].sum():+.1f}")
        print(gaps.head(o.top).round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
