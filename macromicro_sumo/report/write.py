"""report.md and its plots: one writer, and the table of what the report shows
(``ReportKind``: its plots and its parts, in order).

Every part reads the run folder's CSVs and is left out where a stage did not write them.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from macromicro_sumo.evaluation.leader_follower import method_summary
from macromicro_sumo.evaluation.methods import methods_markdown
from macromicro_sumo.files import write_text
from macromicro_sumo.report import plots
from macromicro_sumo.report.alignment import (
    RING_ALIGNMENT,
    SECTION_ALIGNMENT,
    alignment_reference,
    closest_methods,
    paper_policy,
)
from macromicro_sumo.report.deploy import deployment_section
from macromicro_sumo.report.tables import (
    generator_summary,
    markdown_table,
    read_if_present,
    table_section,
)
from macromicro_sumo.truth.section import load_section_truth

ALIGNMENT = "evaluation/macro_alignment.csv"


@dataclass
class Run:
    """One run folder being reported: the scenario, the folder, the run manifest and the
    plots drawn for it (``plots/``, in the order the report shows them)."""

    sc: Any
    out: Path
    manifest: dict[str, Any]
    plots: list[Path] = field(default_factory=list)

    def csv(self, rel: str) -> pd.DataFrame | None:
        return read_if_present(self.out / rel)

    def json(self, rel: str) -> dict[str, Any]:
        return json.loads((self.out / rel).read_text())

    def png(self, name: str) -> Path:
        """Where plot ``name`` goes (``plots/``, made when the first plot is drawn)."""
        (self.out / "plots").mkdir(exist_ok=True)
        return self.out / "plots" / name


Part = Callable[[Run], list[str]]
PlotJob = Callable[[Run], list[Path]]


@dataclass(frozen=True)
class ReportKind:
    """What report.md shows of one kind of road: its plots and its parts, in order."""

    plots: tuple[PlotJob, ...]
    parts: tuple[Part, ...]


@dataclass(frozen=True)
class Table:
    """A part that is one CSV of the run as a table (``shape`` picks or summarises its
    columns) under ``## title`` and the ``intro`` lines (of the scenario); left out where
    the stage did not write the CSV."""

    title: str
    csv: str
    digits: int = 3
    shape: Callable[[pd.DataFrame], pd.DataFrame] = lambda df: df
    intro: Callable[[Any], list[str]] = lambda sc: []

    def __call__(self, r: Run) -> list[str]:
        df = r.csv(self.csv)
        if df is None:
            return []
        return table_section(self.title, self.shape(df), self.digits, self.intro(r.sc))


GENERATOR = "Stage I: generator (held-out snapshots)", "generator/generator_metrics.csv"
MICRO = "Micro consistency (held-out observed actions)", "evaluation/micro_consistency.csv"


# --------------------------------------------------------------------------- plots


def csv_plot(src: str, png: str, draw: Callable[[Path, Path], Path]) -> PlotJob:
    """``draw(run folder / src, plots / png)`` where the stage wrote ``src``. A CSV without
    the columns the plot needs (a generator log of another kind) is left to the report's
    table."""

    def job(r: Run) -> list[Path]:
        if not (r.out / src).is_file():
            return []
        with contextlib.suppress(ValueError):
            return [draw(r.out / src, r.png(png))]
        return []

    return job


def section_truth_plots(r: Run) -> list[Path]:
    """A held-out ground-truth run's time-space diagram per lane; detectors against the
    trajectories and the hidden-count estimate."""
    if not (r.out / "evaluation" / "evaluation_manifest.json").is_file():
        return []
    truth = load_section_truth(r.out / "ground_truth")
    run = int(r.json("evaluation/evaluation_manifest.json")["held_out_runs"][0])
    sec = truth.section
    return [
        plots.plot_time_space(
            {"ground_truth": truth.trajectories},
            r.png("time_space.png"),
            run,
            plots.TIME_SPACE_S,
            sec.length_m,
            sec.offsets_m[1:],
            "Ground truth (dotted: edge borders)",
        ),
        plots.plot_detectors_vs_truth(truth.macro, truth.k_estimate, r.png("detectors.png")),
    ]


def distributions(r: Run) -> list[Path]:
    """Speed and spacing per method; on a section, of the scenes completed with the
    estimated hidden count (what a user has; the true count's are the estimate's cost)."""
    src = r.out / "evaluation" / "eval_samples.csv"
    if not src.is_file():
        return []
    samples = pd.read_csv(src, dtype={"hidden_count": str})
    if "hidden_count" in samples:
        samples = samples[samples["hidden_count"] == "estimated"]
    return [plots.plot_distributions(samples, r.png("distributions.png"))]


TRAINING_PLOTS = (
    csv_plot(
        "generator/generator_train_log.csv", "generator_training.png", plots.plot_generator_training
    ),
    csv_plot("policy/policy_train_log.csv", "policy_training.png", plots.plot_policy_training),
)


# --------------------------------------------------------------------------- shared parts


def alignment_part(
    r: Run,
    heading: Callable[[Any], str],
    road: str,
    columns: tuple[str, ...],
    before: Callable[[pd.DataFrame], list[str]] = lambda align: [],
    after: Callable[[pd.DataFrame], list[str]] = lambda align: [],
) -> list[str]:
    """The methods on the held-out scenes: what each is (``road``'s entries of the methods
    registry), ``columns`` of macro_alignment.csv, and the kind's words ``before`` and
    ``after`` the table."""
    align = r.csv(ALIGNMENT)
    if align is None:
        return []
    return [
        f"## Macro alignment ({heading(r.sc)})",
        "",
        *methods_markdown(road, set(align["method"])),
        *before(align),
        markdown_table(align[[c for c in columns if c in align]]),
        "",
        *after(align),
    ]


def deployment_part(r: Run) -> list[str]:
    return deployment_section(r.out)


def plots_part(r: Run) -> list[str]:
    if not r.plots:
        return []
    return ["## Plots", "", *(f"![{p.stem}](plots/{p.name})" for p in r.plots), ""]


def manifest_part(r: Run) -> list[str]:
    keys = ("timings_s", "versions", "command", "seed")
    text = json.dumps({k: r.manifest[k] for k in keys if k in r.manifest}, indent=2, default=str)
    return ["## Manifest", "", "```json", text, "```", ""]


# --------------------------------------------------------------------------- a section


def section_head(r: Run) -> list[str]:
    """The section, its demand's car-following models, detectors and ground-truth tables."""
    sc, gt = r.sc, r.json("ground_truth/manifest.json")
    kind = "closed loop" if sc.section.closed else "open corridor"
    lines = [
        f"# {sc.name}: macro-micro calibration on a SUMO section",
        "",
        f"Scenario `{sc.source}`, seed {sc.seed}. Section: {len(sc.section.edges)} edges "
        f"({', '.join(sc.section.edges)}), {kind}, {gt['section_length_m']:.0f} m, lanes per "
        f"edge {gt['section_lanes']}.",
        "",
        f"Car-following models of the demand (recorded, not assumed): "
        f"{', '.join(gt['car_following_models'])}. Detectors: {gt['detectors']['count']} "
        f"({gt['detectors']['source']}). Collisions {gt['collisions']}, teleports "
        f"{gt['teleports']}.",
        "",
        "## Ground truth",
        "",
    ]
    for table in (r.csv("ground_truth/runs.csv"), r.csv("ground_truth/vtypes.csv")):
        lines += [] if table is None else [markdown_table(table), ""]
    return lines


def idm_calibrated_part(r: Run) -> list[str]:
    if not (r.out / "evaluation" / "evaluation_manifest.json").is_file():
        return []  # no evaluation in this folder (yet)
    ev = r.json("evaluation/evaluation_manifest.json")
    fit = json.dumps(ev.get("idm_calibrated", {}))
    lines = [f"IDM calibrated on the observed vehicles: {fit}", ""]
    # Why the oracle is in the tables, or left out (``evaluation.idm_true``).
    return lines + ([f"{ev['idm_true']}.", ""] if ev.get("idm_true") else [])


# The paper's ring: its N and its length 2 pi 100 m (where the paper's figures apply).
PAPER_RING = (5, 2 * 3.141592653589793 * 100.0)


def paper_part(r: Run) -> list[str]:
    """The paper's policy and ground truth beside ours, and the issue's targets, on the
    paper's ring (a ring file's section of 5 vehicles on 628.3 m); nothing elsewhere."""
    by_k = r.csv("evaluation/macro_alignment_by_k.csv")
    fleet = getattr(r.sc, "fleet", None)
    if by_k is None or fleet is None or fleet.n_vehicles != PAPER_RING[0]:
        return []
    if not (r.out / "ground_truth" / "manifest.json").is_file():
        return []
    if abs(r.json("ground_truth/manifest.json")["section_length_m"] - PAPER_RING[1]) > 1.0:
        return []
    if "hidden_count" in by_k:
        by_k = by_k[by_k["hidden_count"] == "estimated"]
    return paper_policy(by_k.reset_index(drop=True))


def section_leader_follower(r: Run) -> list[str]:
    """The leader-follower tests on the section's own lane path, where they ran, and what
    the followers were measured against (the evaluation manifest)."""
    summary = r.csv("evaluation/leader_follower_summary.csv")
    manifest = "evaluation/evaluation_manifest.json"
    ev = r.json(manifest).get("leader_follower", {}) if (r.out / manifest).is_file() else {}
    title = "Leader-follower (paper Fig. 3, on the section's lane path)"
    if summary is None:  # skipped (the section too short, a standing obstacle): say why
        return [f"## {title}", "", f"{ev['message']}.", ""] if ev.get("message") else []
    intro = [
        f"{ev.get('message', '')}. Run without the safety layer: a collision is the follower's.",
        "",
    ]
    return table_section(title, method_summary(summary), 3, intro)


# What the report compares of the single pass and the joint refinement (policy rows).
REFINED_COLUMNS = (
    "hidden_count",
    "K",
    "run",
    "mean_speed_mps",
    "std_speed_mps",
    "std_spacing_m",
    "mean_speed_err_mps",
    "spacing_std_err_pct",
    "w1_speed_mps",
    "w1_spacing_m",
    "collisions",
)


def refinement_part(r: Run) -> list[str]:
    """The single pass's policy beside the jointly refined one (``policy.refine_
    iterations``; ``refined/``), by K where the evaluation has a per-K table, and their
    leader-follower RMSEs; nothing where the run has no refinement."""
    name = "macro_alignment_by_k.csv"
    if r.csv(f"refined/evaluation/{name}") is None:
        name = "macro_alignment.csv"
    single, joint = r.csv(f"evaluation/{name}"), r.csv(f"refined/evaluation/{name}")
    if single is None or joint is None:
        return []
    both = pd.concat(
        [
            single[single["method"] == "policy"].assign(run="single pass"),
            joint[joint["method"] == "policy"].assign(run="joint refinement"),
        ]
    )
    if name.endswith("_by_k.csv") and "hidden_count" in both:  # as paper_part: the estimate's
        both = both[both["hidden_count"] == "estimated"]
    keys = [c for c in ("hidden_count", "K") if c in both]
    both = both.sort_values(keys, kind="stable") if keys else both
    iterations = r.sc.policy.refine_iterations
    lines = table_section(
        f"Joint refinement ({iterations} outer iterations) vs single pass",
        both[[c for c in REFINED_COLUMNS if c in both]],
    )
    lf = [r.csv(f"{d}evaluation/leader_follower_summary.csv") for d in ("", "refined/")]
    if lf[0] is not None and lf[1] is not None:
        rows = [
            method_summary(t[t["method"] == "policy"]).assign(run=run)
            for t, run in zip(lf, ("single pass", "joint refinement"), strict=True)
        ]
        table = pd.concat(rows)[["scenario", "run", "mean_rmse_vs_idm_mps", "collisions"]]
        intro = "Leader-follower, policy: mean RMSE against IDM over the trials [m/s]."
        lines += [intro, "", markdown_table(table.sort_values("scenario", kind="stable")), ""]
    return lines


SECTION_REPORT = ReportKind(
    plots=(
        section_truth_plots,
        distributions,
        TRAINING_PLOTS[0],
        csv_plot(
            "evaluation/leader_follower.csv", "leader_follower.png", plots.plot_leader_follower
        ),
        *TRAINING_PLOTS[1:],
    ),
    parts=(
        section_head,
        Table(
            "Hidden count estimated from detector density",
            "evaluation/k_estimate_summary.csv",
            intro=lambda sc: [
                "K = round(vehicles on the section by the detectors) - observed vehicles, "
                "against the count the simulation knows.",
                "",
            ],
        ),
        # Means of the generator's per-snapshot metrics.
        Table(*GENERATOR, shape=generator_summary),
        partial(
            alignment_part,
            heading=lambda sc: "held-out runs",
            road="sumo",
            columns=SECTION_ALIGNMENT,
            before=lambda align: [alignment_reference(align), ""],
            after=closest_methods,
        ),
        Table(
            "Macro alignment by hidden count K (every held-out snapshot at every K)",
            "evaluation/macro_alignment_by_k.csv",
            shape=lambda t: t[[c for c in ("hidden_count", *RING_ALIGNMENT) if c in t]],
        ),
        paper_part,
        refinement_part,
        Table(*MICRO),
        idm_calibrated_part,
        section_leader_follower,
        deployment_part,
        plots_part,
        manifest_part,
    ),
)


def write_report(sc: Any, out: Path | str, manifest: dict[str, Any]) -> Path:
    """report.md of the run folder ``out`` (its plots into ``out/plots``); returns its path."""
    kind = SECTION_REPORT
    r = Run(sc, Path(out), manifest)
    for job in kind.plots:
        r.plots += job(r)
    lines = [line for part in kind.parts for line in part(r)]
    path = r.out / "report.md"
    write_text("\n".join(lines), path)
    return path
