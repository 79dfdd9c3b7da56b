"""Check the links of the documentation: every `[text](path#anchor)` in README.md and
docs/*.md (or the files given) points to an existing file and, with an anchor, to a heading
of that file whose GitHub anchor it is.

GitHub's anchor of a heading (as github-slugger makes it): the heading's text (inline code,
emphasis and links rendered to their text) in lower case, every character that is not a
letter, a digit, '_', '-' or a space dropped, each space a '-'; a repeated anchor in one file
gets '-1', '-2', ... The rule is checked on the README's working links
(`#spacing-spread-at-k--1-and-2-stop-30`, `#scenario-tables-section_configpy`).

    python scripts/check_doc_links.py [FILE.md ...]

Prints one line per broken link (`file:line: target: why`) and exits 1 if there is any, 0
otherwise. Links inside fenced code blocks and inline code are not links; http(s), mailto
and other URLs with a scheme are not checked (nothing here reaches the network).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_FENCE = re.compile(r"^\s{0,3}(```|~~~)")
_HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_INLINE_CODE = re.compile(r"(`+)(.+?)\1")
_LINK = re.compile(r"\[((?:[^\[\]]|\[[^\[\]]*\])*)\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
_SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")
# Anything but letters, digits (any script, as \w), '_', '-' and spaces goes.
_DROP = re.compile(r"[^\w\- ]")


def heading_text(raw: str) -> str:
    """A heading's markdown rendered to its plain text: links to their text, inline code
    to its content, emphasis markers left for the anchor rule to drop."""
    text = _LINK.sub(lambda m: m.group(1), raw)
    return _INLINE_CODE.sub(lambda m: m.group(2), text)


def slug(text: str) -> str:
    """GitHub's anchor of one heading's text (before de-duplication)."""
    return _DROP.sub("", heading_text(text).strip().lower()).replace(" ", "-")


def _lines_outside_fences(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line outside fenced code blocks."""
    out: list[tuple[int, str]] = []
    fence: str | None = None
    for number, line in enumerate(text.split("\n"), start=1):
        marker = _FENCE.match(line)
        if marker:
            if fence is None:
                fence = marker.group(1)
            elif marker.group(1) == fence:
                fence = None
            continue
        if fence is None:
            out.append((number, line))
    return out


def anchors(text: str) -> list[str]:
    """Every heading's anchor in order, repeated ones numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    found: list[str] = []
    taken: set[str] = set()
    for _, line in _lines_outside_fences(text):
        match = _HEADING.match(line)
        if not match:
            continue
        base = slug(match.group(2))
        anchor = base
        while anchor in taken:
            seen[base] = seen.get(base, 0) + 1
            anchor = f"{base}-{seen[base]}"
        taken.add(anchor)
        found.append(anchor)
    return found


def links(text: str) -> list[tuple[int, str]]:
    """(line number, target) of every markdown link outside code."""
    out: list[tuple[int, str]] = []
    for number, line in _lines_outside_fences(text):
        for match in _LINK.finditer(_INLINE_CODE.sub("", line)):
            out.append((number, match.group(2)))
    return out


def broken_links(files: list[Path]) -> list[str]:
    """One line per link of these markdown files whose file or heading does not exist."""
    cache: dict[Path, set[str]] = {}
    problems: list[str] = []
    for path in files:
        text = path.read_text(encoding="utf-8")
        for number, target in links(text):
            if not target or _SCHEME.match(target):
                continue
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path.resolve()
            where = f"{path}:{number}: {target}"
            if not dest.exists():
                problems.append(f"{where}: no file {dest}")
                continue
            if not anchor:
                continue
            if dest.suffix.lower() != ".md" or dest.is_dir():
                problems.append(f"{where}: an anchor into {dest}, which is not a markdown file")
                continue
            if dest not in cache:
                cache[dest] = set(anchors(dest.read_text(encoding="utf-8")))
            if anchor not in cache[dest]:
                problems.append(f"{where}: no heading with anchor #{anchor} in {dest}")
    return problems


def default_files(root: Path = ROOT) -> list[Path]:
    """README.md and docs/*.md of the repository."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    files = [Path(a) for a in args] if args else default_files()
    missing = [f for f in files if not f.is_file()]
    if missing:
        print(f"error: {missing[0]}: no such markdown file", file=sys.stderr)
        return 2
    problems = broken_links(files)
    for line in problems:
        print(line)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
