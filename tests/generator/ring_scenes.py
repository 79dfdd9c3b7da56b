"""Synthetic scenes of the paper's ring read as a closed one-lane section, for the section
generator tests that need no SUMO run: five vehicles with spacings above 60 m (Dirichlet, as
the ring truth draws them)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import (
    SectionConfig,
    SectionGeneratorConfig,
    SectionScenario,
    SumoNetworkConfig,
)

N_VEHICLES = 5
S_MIN_M = 7.0  # the fleet's 5 m length + min_gap_m 2 m
# The generator settings of the training tests: a few seconds each.
FAST = {"epochs": 2, "patience": 10, "batch_size": 16, "hidden_size": 16, "k_source": "truth"}


def ring_scenes(
    section: Section,
    n: int,
    seed: int,
    hide: Callable[[np.random.Generator], np.ndarray | int],
    psi_tail: tuple[float, ...] = (),
) -> SectionSnapshots:
    """``n`` scenes of five vehicles at 10.5-13.5 m/s, those ``hide(rng)`` picks hidden; psi
    from the whole scene: mean speed, L / N, the spacings' std, speed bounds 10 and 14 m/s
    and the minimum spacing, then ``psi_tail``. Draws in that order from ``seed``."""
    rng = np.random.default_rng(seed)
    length = section.length_m
    arc, speed = np.zeros((n, N_VEHICLES)), np.zeros((n, N_VEHICLES))
    observed = np.ones((n, N_VEHICLES), bool)
    psi = np.zeros((n, 6 + len(psi_tail)))
    for i in range(n):
        gaps = 60.0 + rng.dirichlet(np.full(N_VEHICLES, 7.0)) * (length - 60.0 * N_VEHICLES)
        arc[i] = np.mod(
            rng.uniform(0, length) + np.concatenate([[0.0], np.cumsum(gaps[:-1])]), length
        )
        speed[i] = rng.uniform(10.5, 13.5, N_VEHICLES)
        observed[i, hide(rng)] = False
        psi[i] = [speed[i].mean(), length / N_VEHICLES, gaps.std(), 10.0, 14.0, S_MIN_M, *psi_tail]
    return loop_snapshots(arc, speed, observed, psi)


def loop_snapshots(
    arc: np.ndarray, speed: np.ndarray, observed: np.ndarray, psi: np.ndarray
) -> SectionSnapshots:
    """Snapshots of N_VEHICLES cars of 5 m on one lane, one every 5 s of run 0, every car
    recorded; K (true and estimated) is the count of those not observed."""
    n = len(arc)
    k = (~observed).sum(axis=1)
    return SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 5.0,
        lane=np.zeros((n, N_VEHICLES), np.int64),
        arc_m=arc,
        speed_mps=speed,
        length_m=np.full((n, N_VEHICLES), 5.0),
        valid=np.ones((n, N_VEHICLES), bool),
        observed=observed,
        psi=psi,
        k_true=k,
        k_est=k,
    )


def generator_scenario(
    section: Section, base: dict | None = None, **gen: object
) -> SectionScenario:
    """A scenario of ``section`` (its net file is never read) whose ``[generator]`` is
    ``FAST`` (or ``base``) updated by ``gen``."""
    return SectionScenario(
        name="synthetic",
        network=SumoNetworkConfig(net_file="net.xml"),
        section=SectionConfig(edges=list(section.edge_ids), closed=section.closed),
        generator=SectionGeneratorConfig(**(FAST if base is None else base) | gen),  # type: ignore[arg-type]
    )
