"""report.md says why the leader-follower tests were skipped where the evaluation skipped
them (before: the section was left out and the reason was in the log and the evaluation
manifest only; drawn 549 and arterial 521 at stop 37)."""

from __future__ import annotations

import json
from pathlib import Path

from macromicro_sumo.report.write import Run, section_leader_follower

SKIPPED = (
    "leader-follower tests skipped (x.toml): the section is 1869 m long; the test needs 1887 m"
)


def _run(folder: Path, message: str | None) -> Run:
    (folder / "evaluation").mkdir(parents=True)
    ev = {} if message is None else {"leader_follower": {"message": message}}
    (folder / "evaluation" / "evaluation_manifest.json").write_text(json.dumps(ev))
    return Run(None, folder, {})


def test_a_skipped_test_is_reported_with_its_reason(tmp_path: Path) -> None:
    lines = section_leader_follower(_run(tmp_path, SKIPPED))
    assert lines[0].startswith("## Leader-follower")
    assert f"{SKIPPED}." in lines


def test_nothing_where_the_evaluation_said_nothing(tmp_path: Path) -> None:
    assert section_leader_follower(_run(tmp_path / "a", None)) == []
    assert section_leader_follower(Run(None, tmp_path / "none", {})) == []  # no evaluation
