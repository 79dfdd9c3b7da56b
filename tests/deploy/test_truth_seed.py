"""A deployment re-runs the ground truth's runs from the scenario's seed (SUMO seed
seed + run, instrumented vehicles drawn from it): with another seed than the truth's it
would compare other runs with the recorded ones, so ``load_context`` refuses it in one line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pandas as pd
import pytest
from deploy_nets import merge_scenario

from macromicro_sumo.deploy.run import load_context
from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.section import simulate_section


def test_another_seed_than_the_truths_is_refused(tmp_path: Path) -> None:
    path = merge_scenario(tmp_path, {"warmup_s": 10.0, "duration_s": 30.0, "n_runs": 2})
    sc = load_scenario(path)
    gt = simulate_section(sc, tmp_path / "gt", progress=False)
    runs = pd.read_csv(gt / "runs.csv")
    # The recorded runs are seed + run: what the deployment re-runs with the same seed.
    assert (runs["sumo_seed"] == sc.seed + runs["run"]).all()
    assert load_context(sc, gt).held_out  # the truth's own seed: accepted
    other = dataclasses.replace(sc, seed=sc.seed + 1)
    with pytest.raises(UserError) as err:
        load_context(other, gt)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    assert f"seed = {sc.seed + 1}" in msg and f"accepted: seed = {sc.seed}" in msg
