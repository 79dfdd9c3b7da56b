"""Stage settings shared by every scenario kind: the policy and the evaluation (the
deployment's: ``scenario.deploy_settings``)."""

from __future__ import annotations

from dataclasses import dataclass

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import spec


@dataclass(frozen=True, kw_only=True)
class PolicyConfig:
    """Stage II: shared policy trained with PPO on micro + eta * macro."""

    eta: float = spec(0.3, lo=0.0, hi=1e6, doc="macro reward weight eta")
    horizon: int = spec(10, lo=1, hi=100_000, doc="episode length H [policy steps]")
    objective: str = spec("mix", choices=("mix", "micro_only", "macro_only"), doc="ablation switch")
    observation: str = spec(
        "paper",
        choices=("paper", "lookahead", "lookahead_gap", "lookahead_length", "lookahead_gap_length"),
        doc="paper: [v, v_limit, spacing, delta_v]; lookahead adds [next edge's limit, distance to it]; "
        "lookahead_length adds the vehicle's own length [m] (its vType's; not the default: on "
        "drawn mixed-fleet nets it did not bring the trucks' time gaps nearer the truth's); "
        "lookahead_gap is lookahead with the bumper-to-bumper gap to the leader (its own "
        "length: a truck's) in place of the front-to-front spacing, lookahead_gap_length "
        "that with the own length",
    )
    prior: str = spec(
        "none",
        choices=("none", "idm", "gipps", "krauss", "auto"),
        doc="sections: the policy's mean action is the actor's output (none, the paper's), or "
        "a car-following model fitted to the training runs' observed pairs (fixed) plus the "
        "actor's output as a residual: idm (as idm_calibrated) or gipps (Gipps' model: brakes "
        "only as late as is safe, as SUMO's Krauss drivers do) or krauss (Gipps' braking, free "
        "acceleration min(a, (V - v) / T) as Krauss'; policy.prior): the model "
        "reacts to spacing where the observed pairs rarely show close following; auto: "
        "each fitted, the one whose prior alone drives the training runs' demand closest "
        "to the truth's station speeds kept (policy.prior_choice; the manifest says which)",
    )
    residual_bound_mps2: float = spec(
        1.0,
        lo=0.0,
        hi=1e3,
        doc="with a prior: the largest correction the actor adds to it [m/s^2] (B tanh(out / B); "
        "0: the fitted model alone); unbounded, the residual learned to cancel the IDM's braking",
    )
    residual_pairs: str = spec(
        "auto",
        choices=("auto", "driver", "all"),
        doc="with a prior: the observed pairs the residual's likelihood fits: driver leaves out "
        "those accelerating far below the prior (held back by what the observation does not "
        "carry: a merge, a lane change, a queue beyond the section; policy.residual); all "
        "keeps them (before stop 28); auto: driver, except all on a closed one-lane section",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    driver_speed: str = spec(
        "none",
        choices=("none", "drawn", "memory"),
        doc="sections: none, every driver takes the limits as they are (one desired speed); "
        "else each hidden or deployed driver takes them times its own factor: drawn from the "
        "observed vehicles' free-flow speed ratios (drawn), or its own speed ratio where it "
        "was first seen, over their median (memory) (env.driver_speed)",
    )
    driver_entry: str = spec(
        "auto",
        choices=("queued", "held", "auto", "insertion"),
        doc="driver_speed memory: queued, a driver first seen below 0.65 of the observed "
        "median takes drawn's factor; held, also one first seen held by what is ahead "
        "(env.driver_speed.held_at_sight), in Stage II's banks and the deployment (drawn 522 "
        "with merge_reach occupation 3.42 -> 2.73 m/s; netgen_corridor 0.46 -> 0.68); auto, "
        "held where the observed drivers' held first sights are below their top speed, "
        "insertion where their free first sights are as well (since stop 48) "
        "(env.driver_speed.entry_choice; docs/deploy-log.md, Held entries and stop 44); the "
        "default since stop 47 (before: queued); insertion (opt-in), held and also one first "
        "seen at SUMO's departSpeed max insertion speed behind a slower leader "
        "(env.driver_speed.at_insertion)",
        omit_default=True,  # a run trained under "queued" (left out) is retrained
        omit_value="queued",
        # read only by "memory" drivers: elsewhere out of the digest (no retraining)
        omit_unless=("driver_speed", "memory"),
    )
    driver_ratios: str = spec(
        "kaplan_meier",
        choices=("kaplan_meier", "reached"),
        doc="sections, with driver_speed or the krauss prior: the observed drivers' desired-"
        "speed ratios where few cruise freely long enough: kaplan_meier, each other vehicle's "
        "top v / limit is a lower bound; reached, one reached with nothing holding it there "
        "(at a sample within 2% of the top: the next speed not above it, a free gap or a "
        "leader pulling away 0.5 m/s faster) is its ratio, and an exact ratio whose top was "
        "still rising a bound (env.observed_drivers.unheld; measured: docs/deploy.md, The "
        "defaults)",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    driver_follow: str = spec(
        "none",
        choices=("none", "drawn", "auto", "by_vtype", "by_vtype_gap"),
        doc="sections, with the krauss prior: none, every hidden or deployed driver follows at "
        "the prior's one fitted tau; drawn, each at its own tau drawn from the observed "
        "drivers' own fitted taus (evaluation.driver_follow; where at least 30 drivers give "
        "one, else the one tau), carried as a trailing observation column (env.driver_tau); "
        "by_vtype: as drawn, a driver drawing from its own vType's observed drivers' taus "
        "where at least 10 of them give one (IDM cars and trucks keep longer headways than "
        "Krauss cars), else from all drivers'; by_vtype_gap: as by_vtype, from the taus its "
        "vType's drivers keep at pace (the gaps they follow at, not their braking); "
        "auto: drawn or none, the one whose prior alone drives the training runs closer to "
        "the truth's station speeds (as policy.relax_choice; the manifest says which)",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    relax_refit: str = spec(
        "vtype",
        choices=("vtype", "dawdled"),
        doc="sections, with the krauss prior: where the observed pairs' free acceleration a "
        "falls back to the vType's, the relaxation time is refitted next to that a (vtype), "
        "or, where the deployment dawdles the commands (deploy.command_dawdle: auto, a "
        "sigma, or signals on a section with signals), next to SUMO's dawdled mean a (1 - "
        "sigma / 2) (dawdled, opt-in; evaluation.krauss_fit.fit_krauss; docs/deploy-log.md, "
        "stop 51 hP51)",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    hidden_train: tuple[int, int] = spec(
        (1, 4), lo=1, hi=10_000, doc="K range of training episodes"
    )
    seed: int = spec(
        -1,
        lo=-1,
        hi=2**31 - 1,
        doc="PPO's own seed (initial weights, rollouts, minibatches), so a second training "
        "runs on the same ground truth and generator; -1: the scenario's seed",
    )
    updates: int = spec(60, lo=1, hi=1_000_000, doc="PPO updates")
    episodes_per_update: int = spec(32, lo=1, hi=100_000, doc="episodes per rollout")
    epochs: int = spec(4, lo=1, hi=1000, doc="PPO epochs per update")
    minibatches: int = spec(4, lo=1, hi=1000, doc="minibatches per epoch")
    lr: float = spec(3e-3, lo=1e-7, hi=1.0, doc="Adam learning rate")
    gamma: float = spec(0.99, lo=0.0, hi=1.0, doc="discount")
    gae_lambda: float = spec(0.95, lo=0.0, hi=1.0, doc="GAE lambda")
    clip_coef: float = spec(0.2, lo=0.0, hi=10.0, doc="PPO clip")
    vf_coef: float = spec(0.5, lo=0.0, hi=100.0, doc="value loss weight")
    ent_coef: float = spec(0.0, lo=0.0, hi=10.0, doc="entropy bonus weight")
    hidden_size: int = spec(64, lo=4, hi=4096, doc="MLP width")
    init_log_std: float = spec(
        -1.0, lo=-10.0, hi=2.0, doc="initial log std of the action [log m/s^2]"
    )
    lr_schedule: str = spec(
        "constant",
        choices=("constant", "linear"),
        doc="Adam rate over the updates: constant, or linear decay to 0 after the last update "
        "(the final policy is then not one noisy step of a constant rate)",
    )
    micro_pairs: str = spec(
        "all",
        choices=("all", "observed_leader"),
        doc="observed vehicle-steps in r_micro: all (the paper), or only those whose leader is "
        "observed too (behind a hidden leader the spacing and delta_v are generated, not the "
        "ones the recorded action answered)",
    )
    micro_replay: int = spec(
        1,
        lo=1,
        hi=1_000_000,
        doc="rollouts whose observed pairs r_micro uses at each update (1: this update's only, "
        "the paper); with observed_leader the pairs do not depend on the policy",
    )
    macro_speed_scale_mps: float = spec(
        0.0,
        lo=0.0,
        hi=1e3,
        doc="r_macro's L_speed: 0 is the paper's (v / v_mean - 1)^2; s > 0 makes it "
        "((v - v_mean) / s)^2, a bias of s costing as much as the paper's 100% error",
    )
    checkpoint_selection: str = spec(
        "last",
        choices=("last", "val_micro_logp", "val_micro_rmse"),
        doc="policy kept: the last update's, or the update's with the best micro log-likelihood "
        "(val_micro_logp) or the lowest RMSE of its mean action, the deployed one "
        "(val_micro_rmse), on the validation runs (their episodes are then not trained on)",
    )
    checkpoint_every: int = spec(5, lo=1, hi=1_000_000, doc="updates between resumable checkpoints")
    safety: str = spec(
        "sumo",
        choices=("none", "sumo"),
        doc="hidden vehicles' safety layer in training and evaluation rollouts: sumo "
        "caps each speed command at SUMO's safe speed behind what it sees ahead (counted); "
        "none applies it exactly",
    )
    episodes: str = spec(
        "snapshots",
        choices=("snapshots", "demand", "mixed"),
        doc="sections: the episodes PPO's policy gradient learns from: snapshots (H steps from "
        "a generated completion, the paper's), demand (windows of the training runs' own "
        "demand, the hidden population driven as it enters, as a deployment drives it; "
        "env.demand), or mixed (both); the likelihood term uses the snapshot episodes' "
        "recorded pairs in every case",
    )
    demand_horizon_s: float = spec(
        120.0, lo=1.0, hi=1e6, doc="length of a demand episode [s] (SUMO warms up before it)"
    )
    demand_episodes_per_update: int = spec(1, lo=1, hi=10_000, doc="demand episodes per PPO update")
    collision_penalty: float = spec(
        0.0,
        lo=0.0,
        hi=1e6,
        doc="demand episodes: reward subtracted on the step a driven vehicle collides (its "
        "episode ends there in any case, losing its future eta * r_macro)",
    )
    # Joint refinement (pipeline/refinement.py), off by default: left out of the scenario's
    # dict at their defaults, so that a scenario without them keeps its digest and runs.
    refine_iterations: int = spec(
        0,
        lo=0,
        hi=100,
        doc="joint refinement: outer iterations of Algorithm 1 after the single pass (0: none, "
        "the paper's case study); each rolls the policy one step from generated scenes, "
        "fine-tunes the generator towards those hidden states and the policy on its scenes",
        omit_default=True,
    )
    refine_updates: int = spec(
        20, lo=1, hi=1_000_000, doc="PPO updates per refinement iteration", omit_default=True
    )
    refine_epochs: int = spec(
        20, lo=1, hi=100_000, doc="generator epochs per refinement iteration", omit_default=True
    )
    refine_lambda_rec: float = spec(
        1.0,
        lo=0.0,
        hi=1e6,
        doc="weight of the consistency term L_rec between the generator's scene at t + 1 and "
        "the hidden states the policy drove there",
        omit_default=True,
    )


@dataclass(frozen=True, kw_only=True)
class EvaluationConfig:
    """Evaluation protocol: macro alignment rollouts and leader-follower tests."""

    horizon_steps: int = spec(
        10, lo=1, hi=100_000, doc="rollout length for macro alignment [steps]"
    )
    lf_trials: int = spec(20, lo=1, hi=100_000, doc="stochastic leader-follower trials per method")
    lf_duration_s: float = spec(60.0, lo=1.0, hi=1e5, doc="leader-follower test length [s]")
    fcd_episodes: int = spec(
        20, lo=0, hi=100_000, doc="episodes per method and K written as SUMO FCD"
    )


def check_policy(p: PolicyConfig, file: str) -> None:
    """[policy]'s cross-field checks: per-driver taus are the Krauss prior's."""
    if p.driver_follow != "none" and p.prior not in ("krauss", "auto"):
        raise UserError(
            f"{file}: policy.driver_follow = {p.driver_follow!r} needs policy.prior = 'krauss' "
            f"or 'auto' (the taus are the Krauss prior's), not {p.prior!r}; accepted with "
            f"policy.prior = {p.prior!r}: 'none'"
        )
