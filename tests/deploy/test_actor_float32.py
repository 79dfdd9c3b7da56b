"""``policy_batch``'s opt-in float32 actor (``actor_dtype``): the actor's products in
float32, its actions within float32's rounding of the float64 ones, and the default
float64 path the same values as before (``Agent.mean_action`` in float64)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from deploy_nets import merge_scenario

from macromicro_sumo.deploy.policy_batch import ACTOR_ROWS, actor_forward, policy_batch
from macromicro_sumo.deploy.stage import method_drive
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.agent import Agent
from macromicro_sumo.scenario.load import load_scenario


def _agent() -> Agent:
    torch.manual_seed(3)
    agent = Agent(64, observation="lookahead")
    with torch.no_grad():  # an output of a trained size: the float32 rounding shows in it
        agent.actor[-1].weight.normal_(0.0, 1.0)
        agent.actor[-1].bias.fill_(0.3)
    return agent


def _obs(n: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    return np.column_stack(
        [rng.uniform(0, 30, n), np.full(n, 30.0), rng.uniform(5, 250, n)]
        + [rng.uniform(-5, 5, n), np.full(n, 30.0), rng.uniform(0, 500, n)]
    )


@pytest.mark.parametrize("n", [40, ACTOR_ROWS + 72])  # one product a layer, and in chunks
def test_a_float32_actor_is_within_float32_rounding_of_the_float64_one(n: int) -> None:
    agent, obs = _agent(), _obs(n)
    a64 = policy_batch(agent)(obs)
    a32 = policy_batch(agent, "float32")(obs)
    assert a32.dtype == np.float64 and a32.shape == (n,)
    # float32 products: not the float64 values, within float32's rounding of them
    assert np.count_nonzero(a32 != a64)
    np.testing.assert_allclose(a32, a64, rtol=0, atol=1e-5)
    with torch.no_grad():
        want64 = agent.double().mean_action(torch.as_tensor(obs)).numpy()
    np.testing.assert_allclose(a64, want64, rtol=0, atol=1e-12)


def test_the_default_actor_is_float64_and_other_dtypes_are_refused() -> None:
    agent, obs = _agent(), _obs(40)
    np.testing.assert_array_equal(actor_forward(agent)(obs), actor_forward(agent, np.float64)(obs))
    with pytest.raises(ValueError, match="actor_dtype 'float16': accepted float64, float32"):
        policy_batch(agent, "float16")


def test_the_scenario_setting_reaches_every_learned_method(tmp_path: Path) -> None:
    """``deploy.actor_dtype``: float32 by default and in the scenario's digest (the default
    moved from float64, which is left out: ``test_moved_default``);
    it gives each learned method's drive the float32 actor (the same actions as
    ``policy_batch(agent, "float32")``, not the float64 ones), "float64" the float64 one
    (``Agent.mean_action``'s values); another value is refused with one line naming the
    field and what it accepts."""
    path = merge_scenario(tmp_path, {"warmup_s": 10.0, "duration_s": 30.0, "n_runs": 2})
    f32 = load_scenario(path)
    assert (
        f32.deploy.actor_dtype == "float32" and f32.to_dict()["deploy"]["actor_dtype"] == "float32"
    )
    sc = load_scenario(path, {"deploy.actor_dtype": "float64"})
    assert f32.digest() != sc.digest()
    agent, obs = _agent(), _obs(40)
    want32, want64 = policy_batch(agent, "float32")(obs), policy_batch(agent)(obs)
    for name in ("policy", "policy_no_safety", "micro_only", "macro_only"):
        drive, _ = method_drive(name, f32, {name: agent}, None)
        np.testing.assert_array_equal(drive.act(obs), want32)
        drive, _ = method_drive(name, sc, {name: agent}, None)
        np.testing.assert_array_equal(drive.act(obs), want64)
    with pytest.raises(UserError, match="actor_dtype") as err:
        load_scenario(path, {"deploy.actor_dtype": "float16"})
    assert "\n" not in str(err.value) and "float32" in str(err.value)
