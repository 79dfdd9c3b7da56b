"""scripts/bench_safety.py replays recorded safety-layer calls through two copies of
``deploy/brake_plan.py`` and ``deploy/safety.py``: identical code gives the same outputs to
the bit, a changed constant in either file is seen, the copy's safety.py imports the copy's
brake_plan, a missing file is one line, and the calls of a short real Bremen run (SUMO,
an untrained policy on its prior) replay to the bit. Seeded random calls stand in for a
Bremen run in the first tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location("bench_safety", ROOT / "scripts" / "bench_safety.py")
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)
DEPLOY = ROOT / "macromicro_sumo" / "deploy"


def _calls(n_steps: int = 30) -> list:
    rng = np.random.default_rng(7)
    calls = []
    for step in range(n_steps):
        m = 12
        # six new drivers a step on average, the others met before (hand-overs ramp)
        slots = rng.choice(6 * step + m, size=m, replace=False)
        decel = rng.choice([3.0, 4.5], m)
        lead_decel = rng.choice([3.0, 4.5, 9.0], m)
        gap = np.where(rng.random(m) < 0.2, 1e4, rng.uniform(0.0, 60.0, m))
        speed, lead_speed = rng.uniform(0.0, 30.0, m), rng.uniform(0.0, 30.0, m)
        obs = np.column_stack([speed, np.full(m, 30.0), np.zeros(m), speed - lead_speed])
        lead = np.where(rng.random(m) < 0.5, rng.integers(0, m, m), -1)
        cmd = np.maximum(speed + rng.normal(0.0, 2.0, m), 0.0)
        # a red line beyond some leaders (inf: none), as the drivers pass it
        red = np.where(rng.random(m) < 0.3, gap + rng.uniform(0.0, 30.0, m), np.inf)
        handover = (slots, decel, lead_decel, gap, speed, lead_speed, step)
        calls.append(("BrakeHandover", handover))
        safe = (obs, gap, decel, lead_decel, 0.5, lead_speed, red)
        calls.append(("leader_safe_speed", safe))
        cap = (cmd, obs, gap, decel, lead_decel, lead, 0.5, 2.6, 0.2, None, lead_speed, 40.0)
        calls.append(("safety_cap", cap))
    return calls


def _copy(root: Path, edits: dict[str, tuple[str, str]]) -> Path:
    """brake_plan.py and safety.py copied under ``root``, each with its (old, new) edit."""
    folder = root / "macromicro_sumo" / "deploy"
    folder.mkdir(parents=True)
    for name in ("brake_plan.py", "safety.py"):
        text = (DEPLOY / name).read_text()
        if name in edits:
            old, new = edits[name]
            assert old in text
            text = text.replace(old, new)
        (folder / name).write_text(text)
    return root


def test_identical_code_replays_to_the_bit_and_a_change_in_either_file_is_seen(
    tmp_path: Path,
) -> None:
    calls = _calls()
    base = script.base_layer()
    medians, equal = script.compare(base, script.root_layer(ROOT), calls, 0.5, rounds=2, reps=1)
    assert equal and set(medians) == set(script.FUNCTIONS)
    assert all(b > 0 and n > 0 for b, n in medians.values())
    # red_gap is read: leader_safe_speed's outputs with and without it differ on these calls
    with_red = [a for n, a in calls if n == "leader_safe_speed"]
    assert any(
        not np.array_equal(base.leader_safe_speed(*a), base.leader_safe_speed(*a[:-1]))
        for a in with_red
    )
    # A copy whose floor tolerance differs: its counts (safety_cap's) differ.
    tol = {"safety.py": ("SAFETY_TOLERANCE_MPS = 0.01", "SAFETY_TOLERANCE_MPS = 5.0")}
    other = script.root_layer(_copy(tmp_path / "tol", tol))
    assert not script.compare(base, other, calls, 0.5, rounds=1, reps=1)[1]
    # A copy whose hand-over returns faster (brake_plan's): before stop 46 the script
    # replayed the base's brake_plan in both arms and called this the same.
    rate = (
        "HANDOVER_DECEL_RATE_MPS2_PER_S = 0.5",
        "HANDOVER_DECEL_RATE_MPS2_PER_S = 0.001",
    )
    other = script.root_layer(_copy(tmp_path / "rate", {"brake_plan.py": rate}))
    assert not script.compare(base, other, calls, 0.5, rounds=1, reps=1)[1]


def test_the_copys_safety_imports_the_copys_brake_plan(tmp_path: Path) -> None:
    import macromicro_sumo.deploy.brake_plan as plan

    seen = (
        "from __future__ import annotations\n",
        "from __future__ import annotations\n"
        "from macromicro_sumo.deploy.brake_plan import HANDOVER_DECEL_RATE_MPS2_PER_S as SEEN\n",
    )
    rate = ("HANDOVER_DECEL_RATE_MPS2_PER_S = 0.5", "HANDOVER_DECEL_RATE_MPS2_PER_S = 7.0")
    root = _copy(tmp_path, {"safety.py": seen, "brake_plan.py": rate})
    modules = script.layer_modules(root)
    assert modules["deploy.safety"].SEEN == 7.0
    assert modules["deploy.brake_plan"].__file__ == str(
        root / "macromicro_sumo/deploy/brake_plan.py"
    )
    # the base package's modules are as they were
    assert sys.modules["macromicro_sumo.deploy.brake_plan"] is plan
    assert plan.HANDOVER_DECEL_RATE_MPS2_PER_S == 0.5


def test_a_root_without_brake_plan_takes_the_handover_from_safety(tmp_path: Path) -> None:
    """A checkout from before stop 45 (BrakeHandover in safety.py, no brake_plan.py):
    brake_plan's body appended to a copy of safety.py; the layer finds the class there."""
    import macromicro_sumo.deploy.brake_plan as plan

    folder = tmp_path / "macromicro_sumo" / "deploy"
    folder.mkdir(parents=True)
    body = (DEPLOY / "brake_plan.py").read_text().split("from __future__ import annotations\n")[1]
    (folder / "safety.py").write_text((DEPLOY / "safety.py").read_text() + body)
    funcs = script.root_layer(tmp_path)
    assert funcs.BrakeHandover is not plan.BrakeHandover
    assert funcs.BrakeHandover.__module__ == "macromicro_sumo.deploy.safety"
    assert script.compare(script.base_layer(), funcs, _calls(5), 0.5, rounds=1, reps=1)[1]


def test_a_missing_safety_module_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"deploy/safety\.py not found \(NEW_ROOT\)"):
        script.root_layer(tmp_path)


def test_a_short_recorded_bremen_run_replays_to_the_bit(tmp_path: Path) -> None:
    """Real SUMO: Bremen's run 0 for 30 s after its warm-up, driven by an untrained policy
    on its prior (no checkpoint), recorded and replayed through the base and this checkout."""
    calls, dt = script.record(tmp_path / "no_policy.pt", duration_s=30.0)
    counts = {f: sum(n == f for n, _ in calls) for f in script.FUNCTIONS}
    assert dt == 0.5 and all(c > 0 for c in counts.values()), counts
    # leader_safe_speed takes the red-line gaps (None on Bremen: no light)
    assert all(len(a) == 7 for n, a in calls if n == "leader_safe_speed")
    medians, equal = script.compare(
        script.base_layer(), script.root_layer(ROOT), calls, dt, rounds=1, reps=1
    )
    assert equal and all(b > 0 and n > 0 for b, n in medians.values())
