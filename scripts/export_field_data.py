"""Write the field-data example: a simulated Bremen motorway exported as field files.

Simulates ``scenarios/highway_bremen.toml`` (3-4 lanes with an on-ramp) with a shorter
recording, exports per run the instrumented vehicles as NGSIM (feet, lanes from the left,
N(0, 0.3 m) position noise) and the E1 loops as PeMS station files (gzip-compressed: the
readers take ``.csv.gz`` as they are), and writes ``scenarios/highway_bremen_files.toml``:
the same scenario with ``[data] source = "files"`` and the mapping that reads them.

Run: .venv/bin/python scripts/export_field_data.py [--duration 300] [--check]
``--check`` also reads the files back (``macromicro simulate``) and prints the round trip:
psi per snapshot, K estimates and micro pairs against the simulated ground truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from macromicro_sumo.data.section import PSI_FIELDS, SectionTruth, section_snapshots
from macromicro_sumo.evaluation.idm_fit import calibrate_idm, idm_policy_accel
from macromicro_sumo.evaluation.section import micro_pairs
from macromicro_sumo.fielddata.export import observed_rows
from macromicro_sumo.fielddata.schema import LEADER_COLUMNS
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.files import data_toml, export_field_files
from macromicro_sumo.truth.section import load_section_truth, simulate_section

ROOT = Path(__file__).resolve().parents[1]
BASE = ROOT / "scenarios" / "highway_bremen.toml"
FIELD = ROOT / "sumo_nets" / "highway_bremen" / "field_data"
SCENARIO = ROOT / "scenarios" / "highway_bremen_files.toml"
HEADER = """# The Bremen motorway (scenarios/highway_bremen.toml) from field files instead of SUMO runs:
# sumo_nets/highway_bremen/field_data/, written by scripts/export_field_data.py from a simulated
# ground truth (seed 11, {duration:g} s after a {warmup:g} s warm-up, 4 runs): per run the
# instrumented vehicles (10 %) as NGSIM (feet, lanes from the left, 0.3 m position noise) and
# the loops every 250 m as PeMS station files (30 s). File i of each list is run i.
# `macromicro run scenarios/highway_bremen_files.toml --out DIR` runs every stage on them.
"""


def gzip_file(path: Path) -> Path:
    """``path`` compressed to ``path.gz`` (mtime 0: the same data gives the same bytes)."""
    gz = path.with_name(path.name + ".gz")
    with path.open("rb") as src, gzip.GzipFile(gz, "wb", mtime=0) as dst:
        shutil.copyfileobj(src, dst)
    path.unlink()
    return gz


def cleaned(ta: SectionTruth, tb: SectionTruth, sim: Path) -> SectionTruth:
    """The simulated truth with its observed vehicles' speeds replaced by the files'
    cleaned (sEMA) ones: what the cleaning alone does to the micro pairs."""
    rows = pd.concat([observed_rows(sim, int(r))[1] for r in ta.runs], ignore_index=True)
    rows = rows[["run", "time_s", "vehicle_id", "number"]].astype({"number": str})
    files = tb.trajectories[["run", "time_s", "vehicle_id", "speed_mps"]].rename(
        columns={"vehicle_id": "number", "speed_mps": "v_files"}
    )
    back = rows.merge(files.astype({"number": str}), on=["run", "time_s", "number"])
    back = back[["run", "time_s", "vehicle_id", "v_files"]]
    traj = ta.trajectories.merge(back, on=["run", "time_s", "vehicle_id"], how="left")
    traj["speed_mps"] = traj["v_files"].fillna(traj["speed_mps"])
    return dataclasses.replace(ta, trajectories=traj.drop(columns="v_files"))


def round_trip(sim_sc: Path, sim: Path, files_sc: Path, files: Path) -> dict[str, float]:
    """psi, K and micro-pair figures of the files' ground truth against the simulated one."""
    sa, sb = load_scenario(sim_sc), load_scenario(files_sc)
    ta, tb = load_section_truth(sim, sa), load_section_truth(files, sb)
    a, b = section_snapshots(ta, sa, ta.runs), section_snapshots(tb, sb, tb.runs)
    ia = pd.DataFrame({"run": a.run, "time_s": a.time_s, "i": np.arange(len(a))})
    ib = pd.DataFrame({"run": b.run, "time_s": b.time_s, "j": np.arange(len(b))})
    m = ia.merge(ib, on=["run", "time_s"])
    out: dict[str, float] = {"snapshots_sim": len(a), "snapshots_files": len(b)}
    for name in ("mean_speed_mps", "mean_spacing_m"):
        k = PSI_FIELDS.index(name)
        out[f"{name}_max_rel_pct"] = float(np.abs(b.psi[m.j, k] / a.psi[m.i, k] - 1).max() * 100)
    dk = np.abs(b.k_est[m.j] - a.k_est[m.i])
    out |= {"k_est_max_abs_diff": float(dk.max()), "k_est_mean_abs_diff": float(dk.mean())}
    out["k_est_mean_abs_err_vs_truth"] = float(np.abs(a.k_est - a.k_true).mean())
    # Micro pairs and the IDM fitted to them: the files' pairs behind the leader each
    # vehicle measured, against the simulated truth's and the next-observed-vehicle ones.
    oa, aa = micro_pairs(sa, ta, ta.runs, max_pairs=10**9)
    ob, ab = micro_pairs(sb, tb, tb.runs, max_pairs=10**9)
    blind = dataclasses.replace(tb, trajectories=tb.trajectories.drop(columns=list(LEADER_COLUMNS)))
    oc, ac = micro_pairs(sb, blind, tb.runs, max_pairs=10**9)
    out |= {"micro_pairs_sim": len(aa), "micro_pairs_files": len(ab)}
    veh = float(ta.vtypes["length_m"].median())
    fits = {"sim": calibrate_idm(oa, aa, veh), "files": calibrate_idm(ob, ab, veh)}
    fits["files_next_observed"] = calibrate_idm(oc, ac, veh)
    fits["sim_cleaned_speeds"] = calibrate_idm(
        *micro_pairs(sa, cleaned(ta, tb, sim), ta.runs, 10**9), veh
    )
    for name, (p, rmse) in fits.items():
        for key in ("speed_factor", "tau_s", "accel_mps2", "decel_mps2", "min_gap_m"):
            out[f"idm_{name}_{key}"] = float(getattr(p, key))
        out[f"idm_{name}_fit_rmse_mps2"] = rmse
        pred = idm_policy_accel(oa, p, veh) - idm_policy_accel(oa, fits["sim"][0], veh)
        out[f"idm_{name}_vs_sim_on_sim_pairs_rms_mps2"] = float(np.sqrt(np.mean(pred**2)))
    for name, o in (("files", ob), ("files_next_observed", oc)):
        out[f"pairs_{name}_mean_spacing_m"] = float(o[:, 2].mean())
    out["pairs_sim_mean_spacing_m"] = float(oa[:, 2].mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=300.0, help="recorded seconds per run")
    ap.add_argument("--check", action="store_true", help="read back and print the round trip")
    args = ap.parse_args()
    base = load_scenario(BASE)
    sc = dataclasses.replace(
        base, simulation=dataclasses.replace(base.simulation, duration_s=args.duration)
    )
    with tempfile.TemporaryDirectory() as tmp:
        gt = simulate_section(sc, Path(tmp) / "gt", "scripts/export_field_data.py", False)
        if FIELD.exists():
            shutil.rmtree(FIELD)
        data = export_field_files(gt, FIELD, noise_m=0.3, seed=sc.seed)
        for kind in ("trajectories", "stations"):
            data[kind]["files"] = [
                "../sumo_nets/highway_bremen/field_data/" + gzip_file(FIELD / f).name
                for f in data[kind]["files"]
            ]
        text = BASE.read_text().split("\nname = ", 1)[1]
        text = text.replace('"highway_bremen"', '"highway_bremen_files"', 1)
        text = text.replace(
            "duration_s = 600.0", f"duration_s = {args.duration:g}  # of the exported runs"
        )
        header = HEADER.format(duration=args.duration, warmup=sc.simulation.warmup_s)
        SCENARIO.write_text(header + "name = " + text + "\n" + data_toml(data))
        size = sum(p.stat().st_size for p in FIELD.iterdir())
        print(f"wrote {FIELD} ({size / 1e6:.2f} MB) and {SCENARIO}")
        if args.check:
            files = simulate_section(load_scenario(SCENARIO), Path(tmp) / "files", "", False)
            shifted = Path(tmp) / "base.toml"
            shifted.write_text(
                BASE.read_text()
                .replace("duration_s = 600.0", f"duration_s = {args.duration:g}")
                .replace('"../sumo_nets', f'"{ROOT}/sumo_nets')
            )
            for key, value in round_trip(shifted, gt, SCENARIO, files).items():
                print(f"{key}: {value:.4g}")


if __name__ == "__main__":
    main()
