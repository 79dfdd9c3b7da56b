"""What ``policy.driver_entry = "auto"`` resolves to on a ground truth
(``env.driver_speed.entry_choice``): the observed drivers of the train + val runs, how many
of their first sights were held by what is ahead at a speed "queued" keeps (at least
``QUEUED_ENTRY_SHARE`` of the observed median), and those sights' median v / limit over their
driver's top; "held" below ``ENTRY_AT_OWN_SHARE``. Then the same for the free first sights
(neither held nor below that share: the ones every rule keeps as the driver's desired speed),
``free_sights`` and ``free_at_own``: at 1.000 where the net inserts vehicles at their own speed;
below it a kept sight is slower than its driver (drawn 522: 5 at 0.806, every other net of
stop 47 at 1.000; docs/deploy.md, stop 47, hM47). Of those, ``insertion_sights`` at SUMO's
departSpeed "max" insertion speed behind a slower leader (``at_insertion``, what
``policy.driver_entry = "insertion"`` draws as well) and ``insertion_at_own``, the same ratio
over them, and ``other_at_own`` over the rest.

    .venv/bin/python scripts/entry_choice.py SCENARIO.toml GROUND_TRUTH [SCENARIO GROUND_TRUTH ...]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.driver_speed import (
    QUEUED_ENTRY_SHARE,
    at_insertion,
    entry_choice,
    first_sights,
    held_at_sight,
)
from macromicro_sumo.env.driver_speed_ratios import QUANTILE_LEVELS, ObservedDrivers, ratio_estimate
from macromicro_sumo.env.observed_drivers import observed_drivers, ratio_censoring
from macromicro_sumo.road.physics import LIMIT_COLUMN, observes_gap
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth


def _free_first_sights(
    observed: ObservedDrivers, gap_layout: bool, censoring: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observed drivers' first sights (their observation rows), each one's first-sight
    v / limit over its driver's top, and which are free: not ``held_at_sight``, at least
    ``QUEUED_ENTRY_SHARE`` of the median ratio, a known top."""
    idx = first_sights(observed)
    obs = observed.obs[idx]
    keys = [observed.keys[i] for i in idx.tolist()]
    top = np.array([observed.ratio.get(k, observed.lower.get(k, np.nan)) for k in keys])
    ratio = obs[:, 0] / np.maximum(obs[:, LIMIT_COLUMN], 0.1)
    median = np.interp(0.5, QUANTILE_LEVELS, ratio_estimate(observed, censoring).quantiles)
    ok = ~held_at_sight(obs, gap_layout) & (ratio / median >= QUEUED_ENTRY_SHARE)
    ok &= np.isfinite(top) & (top > 0)
    return obs, ratio / np.where(ok, top, 1.0), ok


def _median(at_own: np.ndarray, sel: np.ndarray) -> float:
    return float(np.median(at_own[sel])) if sel.any() else float("nan")


def free_sights(observed: ObservedDrivers, gap_layout: bool, censoring: str) -> tuple[int, float]:
    """How many of the observed drivers' first sights are free (``_free_first_sights``) and
    their median first-sight v / limit over their driver's top (NaN where none):
    ``entry_choice``'s reading of the sights it does not read."""
    if not observed.keys:
        return 0, float("nan")
    _, at_own, ok = _free_first_sights(observed, gap_layout, censoring)
    return int(ok.sum()), _median(at_own, ok)


def insertion_sights(
    observed: ObservedDrivers, gap_layout: bool, censoring: str
) -> tuple[int, float, float]:
    """Of ``free_sights``' sights, how many are ``at_insertion``, their median first-sight v /
    limit over their driver's top, and the same over the other free sights (NaN where none)."""
    if not observed.keys:
        return 0, float("nan"), float("nan")
    obs, at_own, ok = _free_first_sights(observed, gap_layout, censoring)
    ins = ok & at_insertion(obs, gap_layout)
    return int(ins.sum()), _median(at_own, ins), _median(at_own, ok & ~ins)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="SCENARIO.toml GROUND_TRUTH, repeated")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give a ground-truth folder after each scenario")
    print(
        "scenario,observed,held_sights,at_own,entry,free_sights,free_at_own,"
        "insertion_sights,insertion_at_own,other_at_own"
    )
    for toml, data in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        sc = load_scenario(toml)
        truth = load_section_truth(data, sc)
        splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
        drivers = observed_drivers(sc, truth, np.concatenate([splits["train"], splits["val"]]))
        gap, censoring = observes_gap(sc.policy.observation), ratio_censoring(sc)
        c = entry_choice(drivers, gap, censoring)
        n_free, free_at_own = free_sights(drivers, gap, censoring)
        n_ins, ins_at_own, other_at_own = insertion_sights(drivers, gap, censoring)
        print(
            f"{sc.name},{len(set(drivers.keys))},{c.held_sights},{c.at_own:.3f},{c.entry},"
            f"{n_free},{free_at_own:.3f},{n_ins},{ins_at_own:.3f},{other_at_own:.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
