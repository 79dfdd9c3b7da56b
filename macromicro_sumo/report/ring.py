"""report.md: the run's tables and plots, the paper's numbers beside ours, the manifest."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.evaluation.leader_follower import LeaderProfile, method_summary
from macromicro_sumo.evaluation.methods import methods_markdown
from macromicro_sumo.files import write_text
from macromicro_sumo.report import plots
from macromicro_sumo.report.deploy import deployment_section
from macromicro_sumo.report.tables import markdown_table, read_if_present, table_section
from macromicro_sumo.scenario.ring import Scenario

# The paper's ring results (Results and discussions): policy per K, and its ground truth.
PAPER_GT = {
    "mean_speed_mps": 12.06,
    "std_speed_mps": 0.37,
    "mean_spacing_m": 125.66,
    "std_spacing_m": 34.60,
}
PAPER_POLICY_SPEED = {1: 11.55, 2: 11.54, 3: 11.52, 4: 11.53}
PAPER_POLICY_SPEED_STD = "0.78-0.80"
PAPER_POLICY_SPACING_STD = "<= 34.79"
# The generator's held-out figures the report shows (where its metrics have them).
GENERATOR_COLUMNS = (
    "method",
    "K",
    "feasibility_rate",
    "n_no_feasible",
    "projected_vehicles",
    "speed_rel_err",
    "L_mean",
    "L_min",
    "L_max",
    "L_var",
    "pos_err_m",
    "speed_err_mps",
)


def alignment_verdicts(align: pd.DataFrame) -> pd.DataFrame:
    """The issue's targets for ``policy`` per K, measured against the ground truth rows."""
    gt = align[align["method"] == "ground_truth"].set_index("K")
    pol = align[align["method"] == "policy"].set_index("K")
    rows = []
    for k in pol.index:
        g, p = gt.loc[k], pol.loc[k]
        rows.append(
            {
                "K": k,
                "speed error (m/s, <= 0.1)": abs(p["mean_speed_mps"] - g["mean_speed_mps"]),
                "speed std vs GT (%, within 25)": 100
                * (p["std_speed_mps"] / g["std_speed_mps"] - 1),
                "mean spacing - L/N (m)": p["mean_spacing_m"] - g["mean_spacing_m"],
                "spacing std vs GT (%, within 1)": 100
                * (p["std_spacing_m"] / g["std_spacing_m"] - 1),
                "its 95% interval (%)": _spacing_std_interval(p),
                "collisions (0)": str(int(p["collisions"])),
            }
        )
    return pd.DataFrame(rows)


def _spacing_std_interval(row: pd.Series) -> str:
    """'[lo, hi]' of a row's spacing-std error interval in % ('' in files from before it)."""
    lo = row.get("spacing_std_err_ci_lo_pct", np.nan)
    hi = row.get("spacing_std_err_ci_hi_pct", np.nan)
    return "" if pd.isna(lo) or pd.isna(hi) else f"[{lo:+.2f}, {hi:+.2f}]"


# figure -> (column of macro_alignment.csv, how a row scores: lower is better)
FIGURES = {
    "mean-speed error (m/s)": ("mean_speed_err_mps", lambda r, g: r["mean_speed_err_mps"]),
    "speed std vs GT (abs %)": (
        "std_speed_mps",
        lambda r, g: 100 * abs(r["std_speed_mps"] / g["std_speed_mps"] - 1),
    ),
    "spacing std vs GT (abs %)": (
        "std_spacing_m",
        lambda r, g: 100 * abs(r["std_spacing_m"] / g["std_spacing_m"] - 1),
    ),
    "W1 speed (m/s)": ("w1_speed_mps", lambda r, g: r["w1_speed_mps"]),
    "W1 spacing (m)": ("w1_spacing_m", lambda r, g: r["w1_spacing_m"]),
}


def _overlap(a: pd.Series, b: pd.Series) -> bool:
    cols = ("speed_err_ci_lo_mps", "speed_err_ci_hi_mps")
    if not all(c in a.index and c in b.index for c in cols):
        return False
    return bool(a[cols[0]] <= b[cols[1]] and b[cols[0]] <= a[cols[1]])


def figure_winners(
    align: pd.DataFrame, micro: pd.DataFrame | None = None, lf: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Per figure (and K or leader-follower scenario): the best method, and `policy` vs
    `micro_only` stated plainly. On the mean-speed error the two are called a tie when their
    95% intervals (``speed_err_ci_*``) overlap: the difference is then within this
    evaluation's noise."""
    rows = []
    gt = align[align["method"] == "ground_truth"].set_index("K")
    others = align[align["method"] != "ground_truth"]
    for figure, (col, score) in FIGURES.items():
        if col not in align:
            continue
        for k, grp in others.groupby("K", sort=True):
            sc = {r["method"]: score(r, gt.loc[k]) for _, r in grp.iterrows()}
            best = min(sc, key=sc.get)
            row = {"figure": figure, "K / test": str(k), "best": best, "best value": sc[best]}
            row["policy"] = sc.get("policy", np.nan)
            row["micro_only"] = sc.get("micro_only", np.nan)
            if "policy" in sc and "micro_only" in sc:
                p = grp[grp["method"] == "policy"].iloc[0]
                m = grp[grp["method"] == "micro_only"].iloc[0]
                if col == "mean_speed_err_mps" and _overlap(p, m):
                    row["policy vs micro_only"] = "tie (95% intervals overlap)"
                else:
                    row["policy vs micro_only"] = (
                        "policy" if sc["policy"] < sc["micro_only"] else "micro_only"
                    )
            rows.append(row)
    if micro is not None:
        for col, figure in (("nll", "micro NLL"), ("action_rmse_mps2", "action RMSE (m/s2)")):
            sc = micro.dropna(subset=[col]).set_index("method")[col].to_dict()
            if not sc:
                continue
            best = min(sc, key=sc.get)
            row = {"figure": figure, "K / test": "held-out", "best": best, "best value": sc[best]}
            row |= {"policy": sc.get("policy", np.nan), "micro_only": sc.get("micro_only", np.nan)}
            if "policy" in sc and "micro_only" in sc:
                row["policy vs micro_only"] = (
                    "policy" if sc["policy"] < sc["micro_only"] else "micro_only"
                )
            rows.append(row)
    if lf is not None:
        g = lf[lf["method"] != "IDM"].groupby(["scenario", "method"])["rmse_vs_idm_mps"].mean()
        for scenario in g.index.get_level_values(0).unique():
            sc = g.loc[scenario].to_dict()
            best = min(sc, key=sc.get)
            row = {
                "figure": "leader-follower RMSE (m/s)",
                "K / test": scenario,
                "best": best,
                "best value": sc[best],
                "policy": sc.get("policy", np.nan),
                "micro_only": sc.get("micro_only", np.nan),
            }
            if "policy" in sc and "micro_only" in sc:
                row["policy vs micro_only"] = (
                    "policy" if sc["policy"] < sc["micro_only"] else "micro_only"
                )
            rows.append(row)
    return pd.DataFrame(rows)


def make_plots(sc: Scenario, out: Path) -> list[Path]:
    """Every plot whose inputs exist in a run folder, into ``out/plots``."""
    ev, made = out / "evaluation", []
    jobs = [
        (ev / "leader_follower.csv", "leader_follower.png", plots.plot_leader_follower),
        (
            ev / "timespace.csv",
            "time_space.png",
            lambda src, dst: plots.plot_time_space(src, dst, ring_length_m=sc.network.length_m),
        ),
        (ev / "eval_samples.csv", "distributions.png", plots.plot_distributions),
        (
            out / "generator" / "generator_train_log.csv",
            "generator_training.png",
            plots.plot_generator_training,
        ),
        (
            out / "policy" / "policy_train_log.csv",
            "policy_training.png",
            plots.plot_policy_training,
        ),
    ]
    for src, name, fn in jobs:
        if src.is_file():
            (out / "plots").mkdir(exist_ok=True)
            made.append(fn(src, out / "plots" / name))
    return made


def write_report(sc: Scenario, out: Path, manifest: dict[str, Any]) -> Path:
    out = Path(out)
    make_plots(sc, out)
    gt_dir, gen_dir, pol_dir, ev_dir = (
        out / "ground_truth",
        out / "generator",
        out / "policy",
        out / "evaluation",
    )
    parts = [f"# macromicro-sumo report: {sc.name}", ""]
    parts += [
        f"Scenario `{sc.source}` (sha256 `{sc.digest()[:12]}`), seed {sc.seed}. "
        "Every figure below was measured in this run.",
        "",
    ]

    traj = read_if_present(gt_dir / "trajectories.csv")
    runs = read_if_present(gt_dir / "runs.csv")
    if traj is not None and runs is not None:
        parts += [
            "## Ground truth",
            "",
            markdown_table(
                pd.DataFrame(
                    [
                        {
                            "": "paper",
                            "mean speed (m/s)": PAPER_GT["mean_speed_mps"],
                            "speed std (m/s)": PAPER_GT["std_speed_mps"],
                            "mean spacing (m)": PAPER_GT["mean_spacing_m"],
                            "spacing std (m)": PAPER_GT["std_spacing_m"],
                            "collisions": "",
                            "teleports": "",
                        },
                        {
                            "": "ours (SUMO)",
                            "mean speed (m/s)": traj["speed_mps"].mean(),
                            "speed std (m/s)": traj["speed_mps"].std(),
                            "mean spacing (m)": traj["spacing_m"].mean(),
                            "spacing std (m)": traj["spacing_m"].std(),
                            "collisions": int(runs["collisions"].sum()),
                            "teleports": int(runs["teleports"].sum()),
                        },
                    ]
                ),
                2,
            ),
            "",
        ]
        macro = read_if_present(gt_dir / "macro.csv")
        if macro is not None:
            d = macro[macro["source"] == "detectors"].set_index(["run", "begin_s"])
            t = macro[macro["source"] == "trajectories"].set_index(["run", "begin_s"])
            err = {
                c: float(((d[c] - t[c]) / t[c]).abs().max() * 100)
                for c in ("mean_speed_mps", "density_vehpkm", "mean_spacing_m")
            }
            parts += [
                "Detector estimates vs trajectories, worst interval: "
                + ", ".join(f"{k} {v:.2f}%" for k, v in err.items())
                + ".",
                "",
            ]

    gm = read_if_present(gen_dir / "generator_metrics.csv")
    if gm is not None:
        gm = gm[[c for c in GENERATOR_COLUMNS if c in gm]]
    parts += table_section("Stage I: generator (held-out snapshots)", gm, 4)

    align = read_if_present(ev_dir / "macro_alignment.csv")
    if align is not None:
        parts += [
            "## Macro alignment (held-out scenes, rollouts of "
            f"{sc.evaluation.horizon_steps} x {sc.simulation.step_length_s:g} s)",
            "",
            *methods_markdown("ring", set(align["method"])),
        ]
        paper = pd.DataFrame(
            [
                {
                    "K": k,
                    "method": "paper policy",
                    "mean_speed_mps": v,
                    "std_speed_mps": PAPER_POLICY_SPEED_STD,
                    "mean_spacing_m": 125.66,
                    "std_spacing_m": PAPER_POLICY_SPACING_STD,
                }
                for k, v in PAPER_POLICY_SPEED.items()
            ]
        )
        cols = [
            "K",
            "method",
            "mean_speed_mps",
            "std_speed_mps",
            "mean_spacing_m",
            "std_spacing_m",
            "collisions",
            "mean_speed_err_mps",
            "speed_err_ci_lo_mps",
            "speed_err_ci_hi_mps",
            "spacing_std_err_pct",
            "spacing_std_err_ci_lo_pct",
            "spacing_std_err_ci_hi_pct",
            "w1_speed_mps",
            "w1_accel_mps2",
            "w1_spacing_m",
        ]
        parts += [
            markdown_table(align[[c for c in cols if c in align]]),
            "",
            f"The paper (its own ground truth: {PAPER_GT['mean_speed_mps']} m/s, std {PAPER_GT['std_speed_mps']}):",
            "",
            markdown_table(paper, 2),
            "",
            "Targets for `policy`:",
            "",
            markdown_table(alignment_verdicts(align)),
            "",
        ]
    refined = read_if_present(out / "refined" / "evaluation" / "macro_alignment.csv")
    if align is not None and refined is not None:
        cols = [
            "K",
            "mean_speed_mps",
            "std_speed_mps",
            "std_spacing_m",
            "mean_speed_err_mps",
            "w1_speed_mps",
            "w1_spacing_m",
            "collisions",
        ]
        single = align[align["method"] == "policy"][cols].assign(run="single pass")
        joint = refined[refined["method"] == "policy"][cols].assign(run="joint refinement")
        both = pd.concat([single, joint]).sort_values(["K", "run"], kind="stable")
        parts += table_section(
            f"Joint refinement ({sc.policy.refine_iterations} outer iterations) vs single pass",
            both[["K", "run", *cols[1:]]],
        )

    micro = read_if_present(ev_dir / "micro_consistency.csv")
    parts += table_section("Micro consistency (held-out observed actions)", micro, 4)

    lf = read_if_present(ev_dir / "leader_follower_summary.csv")
    if lf is not None:
        parts += table_section(
            "Leader-follower (paper Fig. 3)",
            method_summary(lf),
            intro=[
                f"Follower {LeaderProfile().on_ring(sc).spacing_m:.0f} m behind the leader at the "
                "same speed; the IDM follower has the middle of the "
                f"fleet's IDM ranges; minimum safe gap {sc.evaluation.min_safe_gap_m:g} m; target: mean RMSE "
                "<= 0.3 m/s against the IDM follower.",
                "",
            ],
        )

    if align is not None:
        parts += table_section(
            "Which method wins each figure",
            figure_winners(align, micro, lf),
            4,
            intro=[
                "Lower is better everywhere; `best` among all methods but the ground truth. One "
                "evaluation of one trained policy per method: the training seed moves these "
                "figures too (`scripts/lf_seeds.py` measures that spread).",
                "",
            ],
        )

    parts += deployment_section(out)

    plots = sorted((out / "plots").glob("*.png")) if (out / "plots").is_dir() else []
    if plots:
        parts += ["## Plots", ""] + [f"![{p.stem}](plots/{p.name})" for p in plots] + [""]

    logs = read_if_present(pol_dir / "policy_train_log.csv")
    if logs is not None:
        last = logs.iloc[-1]
        parts += [
            "## Training",
            "",
            f"Policy: {int(last['update'])} updates, final r_macro {last['r_macro']:.4f}, "
            f"r_micro per pair {last['r_micro_per_pair']:.3f}, ground-truth actions clipped for the likelihood: "
            f"{100 * logs['gt_actions_clipped_share'].mean():.2f}%.",
            "",
        ]

    parts += [
        "## Manifest",
        "",
        "```json",
        json.dumps(
            {k: manifest[k] for k in ("timings_s", "versions", "command", "seed") if k in manifest},
            indent=2,
            default=str,
        ),
        "```",
        "",
    ]
    path = out / "report.md"
    write_text("\n".join(parts), path)
    return path
