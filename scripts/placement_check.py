"""Stage I placement on a finished run: the Stage II evaluation's estimated-count completion
(seed sc.seed + 100, generated vehicles as long as ``typical_length``, as
``evaluation/section.py`` builds it), its drops, its hidden count against the truth, its
macro figures, and the evaluation episodes driven by idm_calibrated (deterministic: a
start scene that collides does so in every method's rollouts), counting collisions.

    python scripts/placement_check.py SCENARIO.toml RUN_DIR [--no-drive] [--seed N]

One line of key=value figures: generated, dropped, episodes, collisions (episodes with
one), k_err (mean |placed - true hidden count| per scene), k_bias (mean placed - true),
speed_err (mean |completed mean speed - true|, m/s), speed_bias (mean completed - true),
spacing_err (mean |completed mean spacing - true|, m), std_ratio (completed / true spacing
std, pooled), tight (generated pairs with a front-to-back gap under the minimum gap, on the
section's leaders), digest (md5 of the completed scenes, first 12 characters).
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import libsumo
import numpy as np

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import (
    build_section_bank,
    recorded_min_gap,
    typical_length,
    typical_vclass,
)
from macromicro_sumo.evaluation.idm_fit import calibrate_idm
from macromicro_sumo.evaluation.micro_data import idm_action, micro_pairs
from macromicro_sumo.evaluation.section import held_out_scenes, scenario_safety
from macromicro_sumo.generator.section_metrics import completion_metrics
from macromicro_sumo.generator.section_sampler import complete_section, k_of
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.physics import leader_length_m
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section_truth


def tight_pairs(section, comp, lengths: np.ndarray, gen_len: float, min_gap: float) -> int:
    """Pairs with a generated vehicle in them whose front-to-back gap (spacing less the
    leader's length: recorded, or ``gen_len`` for a generated one) is below ``min_gap``."""
    n = 0
    for s in range(len(comp.valid)):
        on = np.flatnonzero(comp.valid[s])
        lead, sp = section_leaders(section, comp.lane[s, on], comp.arc_m[s, on])
        gen = comp.generated[s, on]
        ln = np.where(
            gen, gen_len, np.pad(lengths[s], (0, comp.valid.shape[1] - lengths.shape[1]))[on]
        )
        has = lead >= 0
        j = np.maximum(lead, 0)
        gap = sp - ln[j]
        n += int((has & (gen | gen[j]) & (gap < min_gap - 1e-6)).sum())
    return n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenario", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--no-drive", action="store_true", help="completion figures only")
    ap.add_argument("--seed", type=int, default=None, help="completion seed (sc.seed + 100)")
    a = ap.parse_args()
    sc = load_scenario(a.scenario)
    truth = load_section_truth(a.run / "ground_truth", sc)
    net = load_section_generator(a.run / "generator" / "generator.pt", sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    h = sc.evaluation.horizon_steps
    snaps, by_k = held_out_scenes(sc, truth, splits["held_out"], h)
    if by_k is not None:
        raise SystemExit(f"{a.scenario}: hidden_per_snapshot scenes are not supported here")
    length = typical_length(truth)
    seed = sc.seed + 100 if a.seed is None else a.seed
    comps = []

    def complete(s):
        c = complete_section(
            net,
            truth.section,
            s,
            k_of(s, "estimate"),
            sc.generator.t_max,
            seed,
            -sc.bounds.accel_mps2[0],
            sc.simulation.step_length_s,
            length,
        )
        comps.append((s, c))
        return c.lane, c.arc_m, c.speed_mps, c.valid, c.generated

    bank = build_section_bank(sc, truth, snaps, complete, horizon=h)
    gen = sum(int(c.generated.sum()) for _, c in comps)
    drop = sum(int(c.dropped.sum()) for _, c in comps)
    kerr, kbias, serr, sbias, derr, std_c, std_t, tight = [], [], [], [], [], [], [], 0
    min_gap = recorded_min_gap(truth)
    gap_floor = 2.0 if min_gap is None else min_gap  # SUMO's default minGap
    for s, c in comps:
        placed = c.generated.sum(axis=1)
        kerr.append(np.abs(placed - s.k_true))
        kbias.append(placed - s.k_true)
        m = completion_metrics(truth.section, s, c, k_of(s, "estimate"))
        serr.append(np.abs(m["mean_speed_mps"] - m["true_mean_speed_mps"]))
        sbias.append(m["mean_speed_mps"] - m["true_mean_speed_mps"])
        derr.append(np.abs(m["mean_spacing_m"] - m["true_mean_spacing_m"]))
        std_c.append(m["std_spacing_m"] ** 2)
        std_t.append(m["true_std_spacing_m"] ** 2)
        tight += tight_pairs(truth.section, c, np.asarray(s.length_m, float), length, gap_floor)
    cat = np.concatenate
    md5 = hashlib.md5()  # the completed scenes, bit for bit
    for _, c in comps:
        for x in (c.lane, c.arc_m, c.speed_mps, c.valid, c.generated):
            md5.update(np.ascontiguousarray(x).tobytes())
    fig = {
        "generated": gen,
        "dropped": drop,
        "k_err": float(np.mean(cat(kerr))),
        "k_bias": float(np.mean(cat(kbias))),
        "speed_err": float(np.nanmean(cat(serr))),
        "speed_bias": float(np.nanmean(cat(sbias))),
        "spacing_err": float(np.nanmean(cat(derr))),
        "std_ratio": float(np.sqrt(np.nanmean(cat(std_c)) / np.nanmean(cat(std_t)))),
        "tight": tight,
        "length": length,
        "min_gap": min_gap,
        "digest": md5.hexdigest()[:12],
    }
    coll = 0
    if not a.no_drive:
        lead_m = leader_length_m(sc.policy.observation, length)
        tr = np.concatenate([splits["train"], splits["val"]])
        obs_tr, acc_tr = micro_pairs(sc, truth, tr)
        idm, _ = calibrate_idm(obs_tr, acc_tr, lead_m)
        act = idm_action(lambda core: idm, lead_m)
        core = SectionCore(
            sc,
            truth.section,
            bank,
            scenario_inputs(sc).net_file,
            seed=sc.seed,
            vclass=typical_vclass(truth),
            safety=scenario_safety(sc),
            replay_min_gap_m=min_gap,
        )
        core.rewarded = False
        rng = np.random.default_rng(seed)
        try:
            for ep in range(len(bank)):
                obs = core.reset(ep)
                for t in range(h):
                    res = core.step(act(core, obs, rng))
                    obs = res.obs
                    if res.collision:
                        coll += 1
                        cs = libsumo.simulation.getCollisions()
                        c0 = cs[0] if cs else None
                        print(f"collision episode {ep} step {t + 1}: {c0}", flush=True)
                    if res.collision or res.truncated:
                        break
        finally:
            core.close()
        fig["episodes"] = len(bank)
        fig["collisions"] = coll
    print(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in fig.items()))


if __name__ == "__main__":
    main()
