"""What ``policy.driver_entry = "auto"`` resolves to on a ground truth
(``env.driver_speed.entry_choice``): the observed drivers of the train + val runs, how many
of their first sights were held by what is ahead at a speed "queued" keeps (at least
``QUEUED_ENTRY_SHARE`` of the observed median), and those sights' median v / limit over their
driver's top; "held" below ``ENTRY_AT_OWN_SHARE``.

    .venv/bin/python scripts/entry_choice.py SCENARIO.toml GROUND_TRUTH [SCENARIO GROUND_TRUTH ...]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env.driver_speed import entry_choice
from macromicro_sumo.env.observed_drivers import observed_drivers, ratio_censoring
from macromicro_sumo.road.physics import observes_gap
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import load_section_truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="SCENARIO.toml GROUND_TRUTH, repeated")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give a ground-truth folder after each scenario")
    print("scenario,observed,held_sights,at_own,entry")
    for toml, data in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        sc = load_scenario(toml)
        truth = load_section_truth(data, sc)
        splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
        drivers = observed_drivers(sc, truth, np.concatenate([splits["train"], splits["val"]]))
        c = entry_choice(drivers, observes_gap(sc.policy.observation), ratio_censoring(sc))
        print(f"{sc.name},{len(set(drivers.keys))},{c.held_sights},{c.at_own:.3f},{c.entry}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
