"""scripts/check_doc_links.py: every `[text](path#anchor)` of README.md and docs/*.md points
to an existing file and a heading with that GitHub anchor; a broken anchor, a missing file
and a repeated heading's anchor are caught on files written here."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "check_doc_links", ROOT / "scripts" / "check_doc_links.py"
)
cdl = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(cdl)


def test_repository_docs_have_no_broken_links() -> None:
    files = cdl.default_files(ROOT)
    assert ROOT / "README.md" in files and len(files) > 3
    assert cdl.broken_links(files) == []


def test_anchor_rule_matches_githubs() -> None:
    # Headings whose GitHub anchors the README links to (and GitHub resolves).
    assert cdl.slug("Spacing spread at K = 1 and 2 (stop 30)") == (
        "spacing-spread-at-k--1-and-2-stop-30"
    )
    assert cdl.slug("Scenario tables (`section_config.py`)") == "scenario-tables-section_configpy"
    assert cdl.slug("Beyond the paper: documented changes") == "beyond-the-paper-documented-changes"
    assert cdl.slug("bench_deploy at stop 36: 0.255x -> 0.263x (hB)") == (
        "bench_deploy-at-stop-36-0255x---0263x-hb"
    )
    assert cdl.slug("The [linked](x.md) **bold** heading") == "the-linked-bold-heading"


def test_repeated_headings_are_numbered_and_code_is_skipped() -> None:
    text = "# Top\n\n### Reproduce\n\n```\n# not a heading\n```\n\n### Reproduce\n\n## Reproduce\n"
    assert cdl.anchors(text) == ["top", "reproduce", "reproduce-1", "reproduce-2"]


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def test_broken_anchor_and_missing_file_fail(tmp_path: Path) -> None:
    _write(tmp_path, "target.md", "# Target\n\n## A section (stop 1)\n\n### Reproduce\n")
    good = _write(
        tmp_path,
        "good.md",
        "[ok](target.md#a-section-stop-1), [file](target.md), [self](#own), "
        "[web](https://example.org/x#y)\n\n## Own\n\n"
        "```\n[in a fence](target.md#nowhere)\n```\n`[in code](target.md#nowhere)`\n",
    )
    assert cdl.broken_links([good]) == []
    assert cdl.main([str(good)]) == 0

    bad = _write(
        tmp_path,
        "bad.md",
        "line one\n[old](target.md#a-section-stop-2)\n[gone](moved.md#x) [here](#nothing)\n",
    )
    problems = cdl.broken_links([bad])
    assert len(problems) == 3
    assert problems[0].startswith(f"{bad}:2: target.md#a-section-stop-2: no heading")
    assert "no file" in problems[1] and ":3:" in problems[1]
    assert "#nothing" in problems[2]
    assert cdl.main([str(bad)]) == 1


def test_missing_markdown_file_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    assert cdl.main([str(tmp_path / "absent.md")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "absent.md" in err
