"""scripts/bench_safety.py replays recorded safety-layer calls through two copies of
``deploy/safety.py``: identical code gives the same outputs to the bit, a changed constant
is seen, and a missing file is one line. Seeded random calls stand in for a Bremen run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

import macromicro_sumo.deploy.safety as base

_spec = importlib.util.spec_from_file_location("bench_safety", ROOT / "scripts" / "bench_safety.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


def _calls(n_steps: int = 30) -> list:
    rng = np.random.default_rng(7)
    calls = []
    for step in range(n_steps):
        m = 12
        slots = rng.choice(40, size=m, replace=False)
        decel = rng.choice([3.0, 4.5], m)
        lead_decel = rng.choice([3.0, 4.5, 9.0], m)
        gap = np.where(rng.random(m) < 0.2, 1e4, rng.uniform(0.0, 60.0, m))
        speed, lead_speed = rng.uniform(0.0, 30.0, m), rng.uniform(0.0, 30.0, m)
        obs = np.column_stack([speed, np.full(m, 30.0), np.zeros(m), speed - lead_speed])
        lead = np.where(rng.random(m) < 0.5, rng.integers(0, m, m), -1)
        cmd = np.maximum(speed + rng.normal(0.0, 2.0, m), 0.0)
        handover = (slots, decel, lead_decel, gap, speed, lead_speed, step)
        calls.append(("BrakeHandover", handover))
        calls.append(("leader_safe_speed", (obs, gap, decel, lead_decel, 0.5, lead_speed)))
        cap = (cmd, obs, gap, decel, lead_decel, lead, 0.5, 2.6, 0.2, None, lead_speed, 40.0)
        calls.append(("safety_cap", cap))
    return calls


def test_identical_code_replays_to_the_bit_and_a_change_is_seen(tmp_path: Path) -> None:
    calls = _calls()
    same = script.safety_module(ROOT, "bench_safety_same")
    medians, equal = script.compare(base, same, calls, 0.5, rounds=2, reps=1)
    assert equal and set(medians) == set(script.FUNCTIONS)
    assert all(b > 0 and n > 0 for b, n in medians.values())
    # A copy whose floor tolerance differs: its counts (safety_cap's) differ.
    folder = tmp_path / "macromicro_sumo" / "deploy"
    folder.mkdir(parents=True)
    text = (ROOT / "macromicro_sumo" / "deploy" / "safety.py").read_text()
    changed = text.replace("SAFETY_TOLERANCE_MPS = 0.01", "SAFETY_TOLERANCE_MPS = 5.0")
    assert changed != text
    (folder / "safety.py").write_text(changed)
    other = script.safety_module(tmp_path, "bench_safety_other")
    assert not script.compare(base, other, calls, 0.5, rounds=1, reps=1)[1]


def test_a_missing_safety_module_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"deploy/safety\.py not found"):
        script.safety_module(tmp_path, "bench_safety_missing")
