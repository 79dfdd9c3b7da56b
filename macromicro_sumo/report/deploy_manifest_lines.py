"""The Deployment section's lines from the stage's manifest (deploy_manifest.json): the safety
layer's floor chosen by ``deploy.safety_floor_on = "auto"`` (``deploy.floor_choice``: per
learned method, the floor kept and both floors' speed RMSE on the training runs it was chosen
on, ``safety_floor_choice``) and how the detector-calibrated IDM's fit ended
(``idm_detectors``, ``deploy.calibrate.calibration_record``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from macromicro_sumo.deploy.stage import MANIFEST
from macromicro_sumo.files import read_manifest

# What each floor raises, in words (``deploy.safety_floor_on``).
FLOOR_WORDS = {
    "all": "any command below it",
    "standing": "only vehicles slower than 1 m/s",
}


def floor_choice_lines(choices: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """One line per method of ``choices`` (method -> ``FloorChoice.record``)."""
    lines = []
    for method, c in choices.items():
        rmse, deployed = c["speed_rmse_mps"], c.get("deployed", list(c["speed_rmse_mps"]))
        figures = " and ".join(f"`{k}` {v:.3f} m/s" for k, v in rmse.items() if k in deployed)
        same = [f"`{k}`" for k in rmse if k not in deployed]
        if same:  # not deployed: "all" raised no command, so these drive the same runs
            figures += f" ({', '.join(same)} the same: `all` raised no command there)"
        runs = ", ".join(str(r) for r in c["training_runs"])
        chosen = c["chosen"]
        lines.append(
            f'- `{method}`: `deploy.safety_floor_on = "auto"` kept `{chosen}` (the floor '
            f"raises {FLOOR_WORDS.get(chosen, chosen)}): speed RMSE {figures} on training "
            f"run(s) {runs}, never the held-out runs above."
        )
    return lines


# How the fit ended (``Calibration.stopped_by``), in words.
STOP_WORDS = {
    "evaluations": "`deploy.calibration_evals` ended it: the same fit on any machine",
    "converged": "it converged",
}


def calibration_line(record: Mapping[str, Any]) -> str:
    """One line on the ``idm_detectors`` fit of a manifest's ``record``. Where the wall clock
    ended it, the line says that a busier machine gets fewer evaluations, so another baseline
    (the ring at load 19: 18 evaluations in 300 s and speed RMSE 0.159 m/s, 30 idle: 0.144)."""
    n, stop = record["evaluations"], record["stopped_by"]
    why = STOP_WORDS.get(stop)
    if stop == "budget":
        why = (
            f"the wall-clock budget `deploy.calibration_budget_s` ended it after "
            f"{record['wall_s']:.0f} s: a busier machine gets fewer evaluations and another "
            f"baseline (a larger budget lets `deploy.calibration_evals` end it)"
        )
    return (
        f"- `idm_detectors`: IDM fitted to the detectors of {len(record['training_runs'])} "
        f"training run(s) in {n} whole-run evaluation(s), loss {record['start_loss']:.3f} -> "
        f"{record['loss']:.3f}; {why or stop}."
    )


def with_manifest_lines(lines: list[str], deploy_dir: Path) -> list[str]:
    """The Deployment section's ``lines`` with the floor choices and the ``idm_detectors``
    fit of ``deploy_dir``'s manifest before its figures (none recorded: ``lines`` as they
    are)."""
    path = deploy_dir / MANIFEST
    manifest = read_manifest(path) if path.is_file() else {}
    extra = floor_choice_lines(manifest.get("safety_floor_choice") or {})
    if manifest.get("idm_detectors"):
        extra.append(calibration_line(manifest["idm_detectors"]))
    if not extra:
        return lines
    at = next((i for i, line in enumerate(lines) if line.startswith("![")), len(lines))
    while at > 0 and not lines[at - 1].strip():  # after the text, before the blank line
        at -= 1
    return [*lines[:at], *extra, *lines[at:]]
