"""The section evaluation drives a policy trained with per-driver desired speeds
(``policy.driver_speed``) with each hidden driver's factor, as training and deployment do,
and every other method without."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from macromicro_sumo.env.driver_speed import QUANTILE_LEVELS, driver_entry, with_driver_factors
from macromicro_sumo.evaluation.section import driven_bank


@dataclass(frozen=True)
class Slots:
    """What ``with_driver_factors`` reads of a ``SectionBank``."""

    valid: np.ndarray
    hidden: np.ndarray
    driver_factor: np.ndarray | None = None


TRUTH = SimpleNamespace(section=None)  # "drawn" reads no positions


def bank() -> Slots:
    rng = np.random.default_rng(3)
    valid = rng.random((6, 8)) < 0.8
    return Slots(valid=valid, hidden=valid & (rng.random((6, 8)) < 0.5))


def test_a_policy_with_factors_gets_them_and_others_do_not() -> None:
    sc = SimpleNamespace(policy=SimpleNamespace(driver_speed="drawn"))
    quantiles = np.quantile(np.random.default_rng(1).normal(1.0, 0.1, 200), QUANTILE_LEVELS)
    agent = SimpleNamespace(driver_speed=torch.as_tensor(quantiles, dtype=torch.float32))
    b = bank()
    got = driven_bank(sc, TRUTH, b, agent, seed=7)
    factor = got.driver_factor
    assert factor is not None
    np.testing.assert_array_equal(factor[~(b.valid & b.hidden)], 1.0)
    hidden = factor[b.valid & b.hidden]
    assert hidden.std() > 0.02  # drawn: the spread of the observed drivers' ratios
    want = with_driver_factors(b, "drawn", quantiles.astype(np.float32).astype(float), 7, None)
    np.testing.assert_allclose(factor, want.driver_factor)
    # The IDM baselines (no agent), a policy trained without factors and a scenario that
    # turned them off drive the bank as it is.
    assert driven_bank(sc, TRUTH, b, None, seed=7) is b
    assert driven_bank(sc, TRUTH, b, SimpleNamespace(driver_speed=None), seed=7) is b
    off = SimpleNamespace(policy=SimpleNamespace(driver_speed="none"))
    assert driven_bank(off, TRUTH, b, agent, seed=7) is b
    # policy.driver_entry "auto" is resolved once by evaluate_section, not per agent's bank;
    # "drawn" drivers do not read it (the same bank as the resolved "queued"), a "memory"
    # driver handed it unresolved refuses it (env.driver_speed.driver_entry)
    auto = SimpleNamespace(policy=SimpleNamespace(driver_speed="drawn", driver_entry="auto"))
    np.testing.assert_array_equal(driven_bank(auto, TRUTH, b, agent, seed=7).driver_factor, factor)
    memory = SimpleNamespace(policy=SimpleNamespace(driver_speed="memory", driver_entry="auto"))
    with pytest.raises(ValueError, match="policy.driver_entry 'auto' is resolved"):
        driver_entry(memory)
