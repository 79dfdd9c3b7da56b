"""Stage III's settings, shared by every scenario kind: which methods are deployed and how
the driven vehicles are driven (``[deploy]``; docs/deploy.md, The defaults)."""

from __future__ import annotations

from dataclasses import dataclass

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import spec

DEPLOY_METHODS = (
    "policy",
    "policy_no_safety",
    "micro_only",
    "macro_only",
    "idm_calibrated",
    "idm_detectors",
    "sumo_default",
    "oracle",
    "oracle_redrawn",
    "oracle_population",
)


@dataclass(frozen=True, kw_only=True)
class DeployConfig:
    """Stage III: every method deployed population-wide over the held-out runs' whole demand."""

    methods: list[str] = spec(
        list(DEPLOY_METHODS),
        choices=DEPLOY_METHODS,
        doc="methods deployed, each into deploy/<method>/ (default: all); policy_no_safety is "
        "the learned policy with safety none, beside policy with the scenario's safety",
    )
    # On by default: the policy alone collided on the Bremen example (0 collisions with it).
    safety: str = spec(
        "sumo",
        choices=("none", "sumo"),
        doc="sumo: SUMO caps the speed commands at its model's safe speed, right of way and "
        "red lights (runs.csv counts how often: safety_acted); none: applied exactly",
    )
    safety_floor_share: float = spec(
        0.2,
        lo=0.0,
        hi=1.0,
        doc="safety sumo: each speed command is raised to at least this share of the lane's "
        "speed limit (at most the safe speed and what the vehicle can reach in a step), so "
        "that no policy holds a car standing where nothing ahead asks for it; 0: no floor "
        "(runs.csv counts the raised commands: floor_acted) [fraction of the limit]",
    )
    safety_floor_on: str = spec(
        "auto",
        choices=("all", "standing", "auto"),
        doc="safety sumo: the vehicles the floor raises: all, any whose command is below it; "
        "standing, only one slower than 1 m/s, so that the floor unsticks a vehicle held "
        "standing and leaves a moving one's braking to its policy; auto, of these two the one "
        "whose deployment on safety_floor_runs training runs has the lower speed RMSE "
        "against the truth's detectors there (a tie: all), chosen per learned method, "
        "recorded in its manifest.json; neither fixed floor is best on every network "
        "(docs/deploy-log.md, Safety layer strictness)",
    )
    safety_floor_runs: int = spec(
        2,
        lo=1,
        hi=10_000,
        doc="safety_floor_on auto: the first this many training runs (never the held-out "
        "ones) each floor is deployed on to choose",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    safety_floor_reaction_s: float = spec(
        0.0,
        lo=0.0,
        hi=5.0,
        doc="safety sumo: the reaction time of the safe speed the floor lifts a standing "
        "vehicle (below 1 m/s) to (deploy.safety.reaction_safe_speed); 0: one step, the "
        "cap's own; the drivers' tau (SUMO's Krauss: 1 s) starts a standing queue nearer "
        "SUMO's lags (docs/deploy-log.md, Floor reaction and the yellow decided at onset). The "
        "cap stays one step [s]",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    start_dawdle: float = spec(
        0.5,
        lo=0.0,
        hi=1.0,
        doc="safety sumo: a driven vehicle's speed command below its accel (as a number) "
        "lowered by the mean of SUMO's Krauss dawdle of a starting driver with this sigma, "
        "v' (1 - sigma dt / 2), after the safe speed's cap and the floor "
        "(deploy.safety.start_dawdled): a standing queue starts as late as SUMO's drivers; "
        "0: off",
        # Moved at stop 49 (hA49, the arterial rules with start_rules signal_lanes): left out
        # of the digest at the old value, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value=0.0,
    )
    start_reaction_s: float = spec(
        1.0,
        lo=0.0,
        hi=5.0,
        doc="safety sumo: a standing driven vehicle's (below 1 m/s) command and floor at most "
        "SUMO's Krauss safe speed with this reaction time (deploy.safety.reaction_safe_speed; "
        "SUMO's Krauss tau: 1 s), so that a standing queue starts as SUMO's drivers do; 0: off "
        "(the one-step cap alone) [s]",
        # Moved at stop 49 (hA49, the arterial rules with start_rules signal_lanes): left out
        # of the digest at the old value, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value=0.0,
    )
    start_rules: str = spec(
        "signal_lanes",
        choices=("all", "signal_lanes"),
        doc="the vehicles start_dawdle and start_reaction_s apply to: all, every driven one; "
        "signal_lanes, those on a lane that can have a signal ahead "
        "(sumo.signal_reach.signal_lanes): a queue at a light starts as SUMO's drivers, a "
        "standing one elsewhere (a motorway's merge queue) as without the rules",
        # Moved at stop 49 (hA49, the arterial rules with start_rules signal_lanes): left out
        # of the digest at the old value, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="all",
    )
    yellow: str = spec(
        "ahead",
        choices=("stop", "onset", "ahead", "sumo"),
        doc="a driven vehicle's yellow light: stop, a stop like a red; onset, decided once, "
        "the first step it sees it (a step after SUMO's drivers): a stop where it can brake "
        "before the line less its jmStoplineGap at its decel, else it passes while the light "
        "stays yellow (never a red; sumo.stop_lines; measured: docs/deploy.md, The "
        "defaults); ahead, onset's rule decided on the last green step but one (the "
        "light's next switch within one step), a step before SUMO's drivers decide and a "
        "step further from the line: it stops more cars than SUMO's rule; sumo, SUMO's own "
        "rule: decided on the switch's step (the last step that reads green: the light "
        "switches at the start of SUMO's step, before its drivers move), a stop where the "
        "distance less the lane's stopOffset holds the braking distance at max(min(3, "
        "emergencyDecel), decel) (sumo.stop_lines)",
        # A deployment setting whose default moved from stop to onset (stop 44): left out of
        # the digest at stop, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="stop",
    )
    green: str = spec(
        "seen",
        choices=("seen", "switch"),
        doc="a driven vehicle's red light that turns green: seen, a stop until the light "
        "shows green (a step after SUMO's drivers, who move off in the step the light "
        "switches in); switch, no stop from the step it switches in (its next switch at the "
        "coming step's start, sumo.stop_lines.StopLineReader.decide_green), as SUMO's drivers",
        # Opt-in (stop 50, hA50; all 4 runs, policy speed RMSE): switch wins on 1706 0.983 ->
        # 0.892 and 528 0.966 -> 0.868, loses on 1164 0.813 -> 0.903, 1407, 521, 837, 1701.
        omit_default=True,
    )
    safety_brake: str = spec(
        "own",
        choices=("own", "matched"),
        doc="safety sumo: the braking each driven vehicle's safe speed plans its stop with: "
        "own, its vType's decel; matched, at least that of the vehicle ahead (an IDM car's "
        "decel is its comfortable braking: own holds it behind a Krauss car to gaps SUMO's "
        "IDM does not keep; docs/deploy-log.md, Safety layer strictness)",
    )
    command_brake: str = spec(
        "decel",
        choices=("bounds", "decel"),
        doc="safety sumo: the hardest braking a driven vehicle's command may ask before the "
        "safety layer: bounds, the scenario's bounds.accel_mps2; decel, at most the braking "
        "the layer plans its stop with (its vType's decel), so that a policy bound below it "
        "brakes no car harder than SUMO's own would where nothing ahead asks for it; the "
        "layer still brakes harder where what is ahead asks for it (deploy.safety."
        "command_brake; measured: docs/deploy.md, The defaults)",
        # A deployment setting whose default moved from bounds to decel (stop 42): left out
        # of the digest at bounds, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="bounds",
    )
    action: str = spec(
        "mean",
        choices=("mean", "sample"),
        doc="learned methods: the acceleration each driven vehicle gets every step: mean, the "
        "policy's deterministic mean action; sample, a draw from its Gaussian (the mean and "
        "its learned std), from a generator seeded by seed and run, before the bounds and the "
        "safety layer (docs/deploy-log.md, Sampled actions)",
        omit_default=True,
    )
    actor_dtype: str = spec(
        "float32",
        choices=("float64", "float32"),
        doc="learned methods: the dtype of the actor's weights and products in the deployment "
        "(deploy.policy_batch; the normalisation, prior, bound and safety layer stay float64): "
        "float32, the dtype torch trains the actor in, its actions within 1e-7 m/s^2 of "
        "float64's and a Bremen step some 10-25 us cheaper; float64, Agent.mean_action's "
        "values in float64 (measured: docs/deploy.md, The defaults)",
        # A deployment setting whose default moved from float64 to float32 (stop 43): left
        # out of the digest at float64, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="float64",
    )
    merge: str = spec(
        "sumo",
        choices=("none", "handover", "sumo"),
        doc="handover: a speed-commanded vehicle that must leave its lane (an acceleration "
        "lane, a lane drop) merges with SUMO's model from where SUMO's lane changer makes "
        "the change urgent (LC2013's strategic look-ahead); sumo: also, a commanded vehicle that "
        "blocks it takes SUMO's cooperative slow-down; none: commands everywhere "
        "(docs/deploy-log.md, Merges)",
    )
    merge_reach: str = spec(
        "occupation",
        choices=("plain", "occupation"),
        doc="merge sumo: occupation, a commanded vehicle that must leave its lane is handed over "
        "from LC2013's usable distance (the distance left less the occupation of the lane it "
        "must reach, so in a queue far before the plain reach) and commanded vehicles yield to "
        "every vehicle that must leave its lane (deploy.merge_yield); plain, the plain reach and "
        "the yield to handed-over vehicles (drawn 549 4.53 -> 3.82 m/s, 501 3.02 -> 2.72, "
        "Bremen 1.15 -> 1.19 with occupation: docs/deploy-log.md, Lane drops; since stop 42 a "
        "vehicle asked to yield is held a step, all 4 runs plain -> occupation: Bremen 1.08 -> "
        "0.91, 501 3.28 -> 1.99, 549 4.33 -> 3.68, 522 2.99 -> 3.46 m/s; the default since "
        "stop 46: on 13 nets it won on 7, tied on 4, lost on 522 and 837, docs/deploy.md); "
        "with merge none or handover the default is plain (set at load, so the recorded "
        "scenario says what runs), and occupation set in the scenario is refused",
        # A deployment setting whose default moved from plain to occupation (stop 46): left
        # out of the digest at plain, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="plain",
    )
    merge_follow: str = spec(
        "last_lane",
        choices=("off", "last_lane"),
        doc="merge sumo, merge_reach occupation: last_lane (the default since stop 50), a "
        "commanded vehicle at 25 m/s or more held after a merge yield on the leftmost lane of "
        "its edge (no lane to move over to) keeps taking SUMO's own slower speed by any amount "
        "while SUMO wants it slower, instead of being released after a step "
        "(deploy.merge_yield.last_lanes). All 4 runs, policy, off -> last_lane: fresh motorway "
        "1803 (4 -> 1 drop) 3.259 -> 2.408 m/s, 501 1.989 -> 1.986, 1802 0.982 -> 0.987; "
        "Bremen, netgen, 549, 522, 563, 1045, 1046, 1169, 1421 md5-equal (hD50, stop 50)",
        # A deployment setting whose default moved from off to last_lane (stop 50): left out
        # of the digest at off, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="off",
    )
    merge_follow_tolerance_mps: float = spec(
        0.5,
        lo=0.0,
        hi=5.0,
        doc="merge_follow last_lane: a blocker that may follow, on a lane moving at 0.6 of its "
        "limit or more, yields where SUMO's own speed is this much below its speed and safe "
        "speed (the merge yield's own tolerance is 1 m/s: at 1.0, stop 50's rule). LC2013 asks "
        "the follower of an urgent merger to fall back by 0.1-0.9 m/s a step; never asked, it "
        "stayed beside the merger, which stood at the lane end. All 4 runs, policy, 1.0 -> 0.5: "
        "1803 2.398 -> 1.410 m/s, 501 2.416 -> 2.260, 522 2.671 -> 2.470, Bremen, netgen, fresh "
        "1902-1904 md5-equal; fresh 1901 3.062 -> 3.498 (hD51, stop 51)",
        # The default moved from 1.0 (stop 50's rule) to 0.5 (stop 51): left out of the
        # digest at 1.0, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value=1.0,
    )
    keep_right: str = spec(
        "off",
        choices=("off", "blocked"),
        doc="merge sumo: blocked, a commanded vehicle at 60 km/h or more passes a slower, "
        "blocked leader (its own leader nearer than 1 s x v + 10 m) on the lane to its left "
        "no faster than LC2013's ban on overtaking on the right lets SUMO's drivers "
        "(deploy.keep_right.keep_right_caps; not with policy.driver_speed drawn); off, no "
        "such cap",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )
    turns: str = spec(
        "handover",
        choices=("off", "limit", "handover"),
        doc="a driven vehicle whose route leaves the section at the coming junction (a turner, "
        "its route asked of SUMO on each section edge with a connection off it; deploy.turns): "
        "handover, it is handed back to SUMO's model before the line, where SUMO would start "
        "braking for the turn; limit, its look-ahead shows the turn's internal-lane limit at "
        "the stop line instead of the next section edge's; off, neither (SUMO braked turners "
        "handed back inside the junction at 5-9 m/s^2 on drawn arterial 528)",
        # A deployment setting whose default moved from off to handover (stop 44): left out
        # of the digest at off, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="off",
    )
    turn_gap: str = spec(
        "sumo",
        choices=("off", "sumo"),
        doc="a driven vehicle whose route change LC2013 finds blocked on a junction edge, and "
        "a driven follower blocking it: sumo, SUMO's own slower speed; off, the command",
        # A deployment setting whose default moved from off to sumo (stop 45): left out of
        # the digest at off, so that a run deployed before is redeployed.
        omit_default=True,
        omit_value="off",
    )
    command_dawdle: float | str = spec(
        "signals",
        lo=0.0,
        hi=1.0,
        choices=("auto", "signals"),
        accepted="a number in [0, 1], 'auto' or 'signals'",
        doc="driven vehicles accelerate at most as Krauss dawdling with this sigma; 0: off; "
        "auto: sigma 0.5 on a vehicle whose policy's Krauss prior's accel exceeds its vType's "
        "dawdled mean a (1 - 0.5 / 2) (a prior that fell back to the vType's a), else off "
        "(a fitted prior's a, or a prior other than krauss); signals: auto on a network with "
        "traffic lights, off on one without",
        omit_default=True,
        omit_value=0.0,
    )
    keep_clear: str = spec(
        "lane1",
        choices=("off", "lane", "lane1"),
        doc="lane: a driven vehicle does not enter a signalised junction where the room on "
        "the lane past it up to its waiting vehicle (below 0.1 m/s; lane1: 1 m/s), less the "
        "vehicles ahead of it, is short of its length and minGap: it waits at its line, as "
        "SUMO's drivers (deploy.keep_clear); off: it follows its leader into the junction",
        # Moved at stop 49 (hA49): left out of the digest at off, so a run deployed before is
        # redeployed.
        omit_default=True,
        omit_value="off",
    )
    fcd_s: float = spec(
        120.0, lo=0.0, hi=1e6, doc="trajectories.csv keeps the first fcd_s recorded seconds [s]"
    )
    share: float = spec(
        1.0,
        accepted="(0, 1]",
        doc="share of the population that is driven, drawn per vehicle (hash of seed, run, id)",
    )
    vtype: str = spec(
        "", doc="instead: only vehicles of this vType are driven (sections; '' = any vType)"
    )
    calibration_budget_s: float = spec(
        300.0,
        lo=1.0,
        hi=1e6,
        doc="idm_detectors: wall-clock budget of the IDM fit to the training runs' detectors [s]",
    )
    calibration_evals: int = spec(
        60, lo=1, hi=100_000, doc="idm_detectors: most whole-run evaluations the fit may use"
    )
    # GEH's 85% rule is for hourly flows; at Bremen's 30 s loops one vehicle is 120 veh/h.
    compare_interval_s: float = spec(
        0.0,
        lo=0.0,
        hi=86400.0,
        doc="interval of deploy_comparison.csv and deploy_summary.csv's shares: the detectors' "
        "intervals pooled into blocks of this length (counts summed, space-mean speeds); 0: "
        "the detectors' own interval; else a multiple of detectors.interval_s; the summary "
        "keeps the detector-interval shares too (docs/deploy.md, GEH) [s]",
    )
    speed_level: str = spec(
        "fit",
        choices=("fit", "tops"),
        doc="sections, the policy with the krauss prior and driver_speed: the deployed drivers' "
        "level; fit, the prior's fitted speed factor; tops, the median of the observed "
        "drivers' top-speed ratios the policy carries, so that each driver's desired speed "
        "is its drawn top speed (policy.checkpoint.with_speed_level; no retraining); drawn 522 "
        "downstream bias -0.93 -> -0.20 m/s over 11 PPO seeds, but highway_bremen 0.914 -> "
        "1.423 and netgen_corridor 0.460 -> 0.627 m/s (docs/deploy.md, stop 50)",
        omit_default=True,  # the digests of scenarios that do not set it stay as they were
    )


def check_deploy(
    d: DeployConfig,
    file: str,
    detector_interval_s: float | None = None,
    run_s: float | None = None,
    set_keys: frozenset[str] | None = None,
) -> None:
    """[deploy]'s cross-field checks; ``detector_interval_s`` and ``run_s`` (warm-up and
    duration): the detectors' period and a run's length where the scenario fixes them (None:
    field data's own, checked when the deployment is compared). ``set_keys``: the [deploy]
    keys the scenario sets (None: every key counts as set); a default is not refused."""
    if run_s is not None and d.compare_interval_s > run_s + 1e-9:
        raise UserError(
            f"{file}: deploy.compare_interval_s = {d.compare_interval_s:g} exceeds a run "
            f"(simulation.warmup_s + duration_s = {run_s:g} s); accepted: 0 or at most {run_s:g}"
        )
    k = d.compare_interval_s / detector_interval_s if detector_interval_s else 1.0
    if d.compare_interval_s and (k < 1 - 1e-6 or abs(k - round(k)) > 1e-6):
        raise UserError(
            f"{file}: deploy.compare_interval_s = {d.compare_interval_s:g} is not a multiple of "
            f"detectors.interval_s = {detector_interval_s:g}; accepted: 0 (the detectors' own) "
            f"or k x {detector_interval_s:g} s, k = 1, 2, ..."
        )
    if d.keep_right != "off" and d.merge != "sumo":
        raise UserError(
            f"{file}: deploy.keep_right = {d.keep_right!r} needs deploy.merge = 'sumo', not "
            f"{d.merge!r}; accepted with deploy.merge = {d.merge!r}: 'off'"
        )
    # The default occupation with merge none or handover acts as plain (``SectionSpeedDriver``):
    # only occupation the scenario asks for needs merge sumo.
    said_reach = set_keys is None or "merge_reach" in set_keys
    if said_reach and d.merge_reach != "plain" and d.merge != "sumo":
        raise UserError(
            f"{file}: deploy.merge_reach = {d.merge_reach!r} needs deploy.merge = 'sumo', not "
            f"{d.merge!r}; accepted with deploy.merge = {d.merge!r}: 'plain'"
        )
    if not 0.0 < d.share <= 1.0:
        raise UserError(f"{file}: deploy.share = {d.share!r} is out of range; accepted: (0, 1]")
    if not d.methods:
        raise UserError(
            f"{file}: deploy.methods is empty; accepted: one or more of {', '.join(DEPLOY_METHODS)}"
        )
    if len(set(d.methods)) != len(d.methods):
        raise UserError(f"{file}: deploy.methods lists a method twice")
