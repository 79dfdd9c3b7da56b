"""scripts/bench_sumo_step.py's replay is the policy run it recorded: SUMO's own step timed
under the policy's commands without the driver's work between steps is the same run (real
SUMO, the Bremen example's demand, run 0), and the script leaves Simulation as it was."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from conftest import ROOT

from macromicro_sumo.sumo.simulation import Simulation

_spec = importlib.util.spec_from_file_location(
    "bench_sumo_step", ROOT / "scripts" / "bench_sumo_step.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def test_the_replay_is_the_policy_run_and_simulation_is_put_back(tmp_path: Path) -> None:
    before = {n: Simulation.__dict__[n] for n in (*script.SENT, "step")}
    # No checkpoint: bench_deploy's untrained residual on the scenario's prior.
    rows = script.run_variants(["replay", "oracle"], 1, tmp_path / "none.pt")
    assert set(rows) == {"policy", "replay", "oracle"}
    (policy,), (replay,), (oracle,) = rows["policy"], rows["replay"], rows["oracle"]
    # The same vehicle-steps and the same speed commands, to the bit; some were sent.
    assert replay[1:] == policy[1:]
    assert policy[1] > 10_000 and policy[2] != oracle[2]
    assert all(r[0] > 0 for r in (policy, replay, oracle))
    assert {n: Simulation.__dict__[n] for n in before} == before
