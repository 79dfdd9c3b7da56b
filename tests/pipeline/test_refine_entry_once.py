"""The joint refinement reads ``policy.driver_entry = "auto"``'s rule and the drivers' speed
quantiles once (the observed drivers of the train + val runs), not at every episode build:
the same episodes as the policy stage's own resolution, on the small paper ring (real
SUMO, torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_RING
from tiny_pass import tiny_single_pass

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.env import driver_speed
from macromicro_sumo.env import observed_drivers as observed_drivers_module
from macromicro_sumo.generator.section_train import load_section_generator
from macromicro_sumo.pipeline.build import fit_residual_prior
from macromicro_sumo.pipeline.refinement import _episodes, refine
from macromicro_sumo.truth.section import load_section_truth

pytestmark = pytest.mark.usefixtures("keep_torch_threads")

TINY_AUTO = {
    **SMALL_RING,
    "generator.epochs": 2,
    "policy.updates": 1,
    "policy.episodes_per_update": 2,
    "policy.driver_speed": "memory",
    "policy.driver_entry": "auto",
    "policy.refine_iterations": 2,
    "policy.refine_updates": 1,
    "policy.refine_epochs": 1,
}


def test_refinement_resolves_the_entry_once_with_the_same_episodes(
    small_ring_gt: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sc, gen, pol = tiny_single_pass(tmp_path, small_ring_gt, TINY_AUTO)
    # The episodes of the rule resolved beforehand are those section_episodes resolves.
    truth = load_section_truth(small_ring_gt, sc)
    splits = split_runs(truth.runs, sc.generator.held_out_fraction, sc.seed)
    runs = np.concatenate([splits["train"], splits["val"]])
    resolved = driver_speed.resolved_entry(sc, truth, runs)[0]
    assert resolved.policy.driver_entry in ("queued", "held", "insertion")
    net = load_section_generator(gen, sc)
    own, _ = _episodes(sc, truth, net, splits)
    once, _ = _episodes(resolved, truth, net, splits)
    for name in ("driver_factor", "arc0_m", "speed0_mps", "hidden", "valid"):
        assert np.array_equal(getattr(own.bank, name), getattr(once.bank, name)), name
    assert (own.bank.driver_factor != 1.0).any()  # memory drivers drawn: a real comparison
    # Two iterations (three episode builds): one read of the observed drivers for the rule
    # and one for the speed quantiles (before: one of each per build).
    reads: dict[str, int] = {"entry": 0, "quantiles": 0}
    for module, name in ((driver_speed, "entry"), (observed_drivers_module, "quantiles")):
        real = module.observed_drivers

        def counted(*a, _real=real, _name=name, **k):
            reads[_name] += 1
            return _real(*a, **k)

        monkeypatch.setattr(module, "observed_drivers", counted)
    manifest = refine(
        sc, small_ring_gt, gen, pol, tmp_path / "refined",
        progress=False, fit_prior=fit_residual_prior,
    )  # fmt: skip
    assert len(manifest["iterations"]) == 2
    assert reads == {"entry": 1, "quantiles": 1}
