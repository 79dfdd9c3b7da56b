"""The Deployment section's lines on the safety layer's floor chosen by
``deploy.safety_floor_on = "auto"`` (``deploy.floor_choice``): per learned method, the floor
kept and both floors' speed RMSE on the training runs it was chosen on, from the stage's
manifest (deploy_manifest.json's ``safety_floor_choice``)."""

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


def with_floor_choices(lines: list[str], deploy_dir: Path) -> list[str]:
    """The Deployment section's ``lines`` with the floor choices of ``deploy_dir``'s
    manifest before its figures (none recorded: ``lines`` as they are)."""
    path = deploy_dir / MANIFEST
    choices = read_manifest(path).get("safety_floor_choice") if path.is_file() else None
    if not choices:
        return lines
    at = next((i for i, line in enumerate(lines) if line.startswith("![")), len(lines))
    while at > 0 and not lines[at - 1].strip():  # after the text, before the blank line
        at -= 1
    return [*lines[:at], *floor_choice_lines(choices), *lines[at:]]
