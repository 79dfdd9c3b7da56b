"""What the policy tests share: the small paper ring's scenario (its closed one-lane section),
an episode bank completed with the true hidden states (which isolates Stage II from the
generator), its env core, observation pairs of a road in the lookahead layout, and a policy
with a Gipps prior."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from conftest import SMALL_RING, write_scenario

from macromicro_sumo.data.section import section_snapshots, split_runs
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.env.section_bank import SectionBank, build_section_bank
from macromicro_sumo.env.section_envs import true_section_completion
from macromicro_sumo.evaluation.idm_fit import GippsParams
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.sumo.inputs import scenario_inputs
from macromicro_sumo.truth.section import load_section, load_section_truth


def ring_scenario(folder: Path, overrides: dict[str, Any]) -> SectionScenario:
    """The paper ring with ``SMALL_RING`` and ``overrides`` (keys of the stages after the
    simulation: ``small_ring_gt`` is its ground truth), written into ``folder``."""
    assert not any(k.startswith(("simulation.", "fleet.", "seed")) for k in overrides)
    # Without ring_paper's IDM prior unless asked: PPO needs a prior's fitted parameters,
    # which these tests pass only where they test a prior.
    base = {**SMALL_RING, "policy.prior": "none"}
    return load_scenario(write_scenario(folder, {**base, **overrides}))


def true_state_bank(
    sc: SectionScenario,
    gt_dir: Path,
    k: int | tuple[int, int] = (1, 3),
    split: str = "train+val",
) -> tuple[SectionBank, dict[str, np.ndarray]]:
    """Episodes of ``split``'s runs ("train", or "train+val") with ``k`` hidden vehicles
    (or K drawn per snapshot from a range) completed by the true hidden states; and the
    run split."""
    truth = load_section_truth(gt_dir, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    runs = np.concatenate([splits[s] for s in split.split("+")])
    snaps = section_snapshots(truth, sc, runs, (k, k) if isinstance(k, int) else k)
    bank = build_section_bank(sc, truth, snaps, true_section_completion, sc.policy.horizon, 0)
    return bank, splits


def ring_core(sc: SectionScenario, bank: SectionBank, seed: int = 0) -> SectionCore:
    """The env core over ``bank`` on the ring's section (``policy.ppo``'s default core)."""
    return SectionCore(sc, load_section(sc)[1], bank, scenario_inputs(sc).net_file, seed=seed)


def lookahead_pairs(
    rng: np.random.Generator,
    n: int,
    speed_mps: tuple[float, float],
    limit_mps: float,
    free_spacing_m: float,
    follow_spacing_m: tuple[float, float],
    closing_mps: tuple[float, float],
    next_limit_m: float,
) -> np.ndarray:
    """Observations (lookahead layout) of recorded pairs on a road limited to ``limit_mps``:
    own speed uniform in ``speed_mps``; every other pair free (spacing ``free_spacing_m``, no
    closing speed), the rest following at ``follow_spacing_m`` closing at ``closing_mps``;
    the next limit (the same) up to ``next_limit_m`` ahead. Draws from ``rng`` in that order."""
    obs = np.zeros((n, 6), dtype=np.float32)
    obs[:, 0] = rng.uniform(*speed_mps, n)
    obs[:, 1] = obs[:, 4] = limit_mps
    following = rng.uniform(*follow_spacing_m, n)
    obs[:, 2] = np.where(np.arange(n) % 2 == 0, free_spacing_m, following)
    obs[:, 3] = np.where(obs[:, 2] < free_spacing_m, rng.uniform(*closing_mps, n), 0.0)
    obs[:, 5] = rng.uniform(0.0, next_limit_m, n)
    return obs


def gipps_agent(
    gipps: GippsParams, length_m: float, dt_s: float, hidden: int = 16, **kwargs: Any
) -> Agent:
    """A policy whose mean is the Gipps model ``gipps`` plus the actor's residual;
    ``kwargs`` go to ``Agent`` (observation, shift_scale, residual_bound_mps2)."""
    params = {**gipps.as_dict(), "veh_length_m": length_m, "dt_s": dt_s}
    return Agent(hidden, prior="gipps", prior_params=params, **kwargs)
