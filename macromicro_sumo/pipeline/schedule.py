"""The pipeline's stages and the rule that runs them: each stage is skipped when its
manifest records the scenario's values of every key it depends on (``Stage``) and no stage
it reads from was redone in this call; stages that do not read each other run side by side
(``pipeline.parallel``). ``pipeline.build`` makes the stages.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import check_outputs, prepare_out_dir, write_json
from macromicro_sumo.manifest import build_manifest
from macromicro_sumo.pipeline.parallel import can_ship, cpu_s, run_side_by_side
from macromicro_sumo.policy.chosen_prior import settings_of


@dataclass(frozen=True)
class Stage:
    """A pipeline stage: done when ``manifest`` records the scenario's settings for every
    key outside ``ignores`` (the keys neither it nor the stages it ``needs`` read, dotted:
    a table or one key) and no stage in ``needs`` was redone in this call."""

    name: str
    manifest: Path
    run: Callable[[], Any]
    needs: tuple[str, ...] = ()
    ignores: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()  # keys under ``ignores`` that it reads all the same
    # What the stages reading it take from its outputs (None: none readable), read before
    # and after it runs: a stage redone whose result is what it was does not redo them
    # (the prior's choice redone after a [deploy] edit that left it as it was).
    result: Callable[[], Any] | None = None


def stage_settings(scenario: dict[str, Any], stage: Stage) -> dict[str, Any]:
    """The dotted keys of ``scenario`` (``to_dict`` or a manifest's copy) that ``stage``
    depends on, with their values as a manifest's JSON holds them."""
    return settings_of(scenario, stage.ignores, stage.reads)


def _why_redo(stage: Stage, sc: Any, redone: set[str]) -> str | None:
    """None when ``stage`` is done for ``sc``; else why it runs (printed with progress)."""
    if not stage.manifest.is_file():
        return "no outputs yet"
    try:
        manifest = json.loads(stage.manifest.read_text())
        recorded = manifest["scenario"]
        # Outputs lost, cut short or edited since the stage wrote them: it runs again.
        check_outputs(
            stage.manifest.parent,
            manifest,
            rerun="redoing the stage",
            manifest_name=stage.manifest.name,
        )
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        return f"{stage.manifest.name} unreadable"
    except UserError as exc:
        return str(exc)
    have, want = stage_settings(recorded, stage), stage_settings(sc.to_dict(), stage)
    changed = sorted(k for k in have.keys() | want.keys() if have.get(k) != want.get(k))
    if changed:
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        return f"{', '.join(changed[:3])}{more} changed"
    inputs = [n for n in stage.needs if n in redone]
    return f"{', '.join(inputs)} redone" if inputs else None


def run_stages(
    sc: Any, stages: list[Stage], out: Path, command: str, progress: bool, jobs: int = 1
) -> dict[str, Any]:
    """Run ``stages`` in order, skipping those done for this scenario (``Stage``); per-stage
    wall and CPU times go into ``out/manifest.json`` (returned).

    With ``jobs`` > 1, stages whose inputs are all ready and that do not read each other
    (the policy and its ablations; the evaluation and the deployment) run side by side in
    worker processes (``pipeline.parallel``): the same outputs, sooner on several cores."""
    previous = _previous_timings(out / "manifest.json")
    timings: dict[str, Any] = {}
    cpu: dict[str, float] = {}
    redone: set[str] = set()
    pending = list(stages)
    while pending:
        names = {s.name for s in pending}
        ready = [s for s in pending if not names.intersection(s.needs)]
        pending = [s for s in pending if s not in ready]
        todo: list[tuple[Stage, str]] = []
        results: dict[str, Any] = {}
        for stage in ready:
            why = _why_redo(stage, sc, redone)
            if why is None:
                timings[stage.name] = previous.get(stage.name, "skipped (outputs existed)")
                if progress:
                    print(f"[{stage.name}] skipped: outputs exist for these settings")
            else:
                todo.append((stage, why))
                if stage.result is not None:
                    results[stage.name] = stage.result()
        if jobs > 1 and len(todo) > 1 and all(can_ship(s.run) for s, _ in todo):
            clocks = _side_by_side(todo, jobs, progress)
        else:
            clocks = {stage.name: _in_process(stage, why, progress) for stage, why in todo}
        for stage, _ in todo:
            same = stage.result is not None and results[stage.name] is not None
            if same and stage.result() == results[stage.name]:  # its readers need not redo
                if progress:
                    print(f"[{stage.name}] gave what it gave before: the stages reading it stand")
            else:
                redone.add(stage.name)
            timings[stage.name] = round(clocks[stage.name][0], 3)
            cpu[stage.name] = round(clocks[stage.name][1], 3)
    manifest = build_manifest(sc, command, stage="run")
    manifest["timings_s"] = timings
    manifest["cpu_s"] = cpu  # this call's stages only (a skipped stage has none)
    write_json(manifest, out / "manifest.json")
    return manifest


def _in_process(stage: Stage, why: str, progress: bool) -> tuple[float, float]:
    """Run one stage here; its (wall, CPU) seconds."""
    if progress:
        print(f"[{stage.name}] running: {why}")
    w0, c0 = time.perf_counter(), cpu_s()
    stage.run()
    wall = time.perf_counter() - w0
    if progress:
        print(f"[{stage.name}] done in {wall:.1f} s")
    return wall, cpu_s() - c0


def _side_by_side(
    todo: list[tuple[Stage, str]], jobs: int, progress: bool
) -> dict[str, tuple[float, float]]:
    """Run the stages of ``todo`` in ``jobs`` worker processes; their (wall, CPU) seconds."""
    # Their folders, locked by this run until it ends as if it ran them itself.
    held = [prepare_out_dir(stage.manifest.parent) for stage, _ in todo]
    if progress:
        for stage, why in todo:
            print(f"[{stage.name}] running: {why}")
        print(f"[{', '.join(s.name for s, _ in todo)}] side by side in {jobs} processes")
    clocks = run_side_by_side([(s.name, s.run) for s, _ in todo], held, jobs)
    if progress:
        for stage, _ in todo:
            print(f"[{stage.name}] done in {clocks[stage.name][0]:.1f} s")
    return clocks


def _previous_timings(path: Path) -> dict[str, Any]:
    """Stage timings of an earlier, interrupted or finished, run into the same folder."""
    try:
        return dict(json.loads(path.read_text()).get("timings_s", {}))
    except (OSError, json.JSONDecodeError):
        return {}
