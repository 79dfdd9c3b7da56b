"""Atomic file output: every result appears whole or not at all.

Writers go to a temporary name in the same folder and ``os.replace`` it into place,
so an interrupted run never leaves a half-written CSV, checkpoint or manifest.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import pandas as pd

from macromicro_sumo.errors import UserError

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs are ordinary files
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_csv(df: pd.DataFrame, path: Path | str, float_format: str = "%.6f") -> None:
    """Write a CSV atomically with a fixed float format (same seed -> same bytes)."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format=float_format, lineterminator="\n")


def write_json(obj: Any, path: Path | str) -> None:
    """Write JSON atomically, keys sorted so that equal content gives equal bytes."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def write_text(text: str, path: Path | str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def file_sha256(path: Path | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# Every folder the tool writes carries this file. A folder is replaced only when it has it,
# so a user's own ``DIR/sumo`` (their network, say) is never deleted by ``--out DIR``.
OUTPUT_MARK = ".macromicro-output"


def mark_output(folder: Path) -> None:
    """Mark ``folder`` as written by this tool (it may be replaced by a later run)."""
    (folder / OUTPUT_MARK).write_text("written by macromicro-sumo; a later run may replace it\n")


def check_out_path(out: Path | str, inputs: Iterable[Path | str] = ()) -> None:
    """Refuse output folders that would put the user's files at risk.

    ``/``, the home folder, an input file itself, or a folder holding an input: a stage
    replaces its output folders, so none of these may be one.
    """
    where = Path(out).expanduser().resolve()
    if where == Path(where.anchor) or where == Path.home().resolve():
        raise UserError(f"--out {out}: refusing the root or home folder; pass a folder of its own")
    for item in inputs:
        src = Path(item).expanduser().resolve()
        if src == where or where in src.parents:
            raise UserError(
                f"--out {out}: holds the input {item}; pass an output folder outside the inputs"
            )


def prepare_out_dir(out: Path | str, inputs: Iterable[Path | str] = ()) -> Path:
    """Check that ``out`` can hold outputs: a folder or nothing yet, never a file."""
    check_out_path(out, inputs)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: output folder is an existing file; pass a folder path")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out}: cannot create output folder ({exc.strerror})") from None
    return out


@contextlib.contextmanager
def staging_dir(out: Path) -> Iterator[Path]:
    """A scratch folder inside ``out`` whose contents move into ``out`` only on success.

    Stages write many files; staging them keeps ``out`` free of partial results when a
    stage fails half-way (bad input found late, SUMO error, Ctrl-C).
    """
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        yield stage
        items = sorted(stage.iterdir(), key=lambda p: ("manifest" in p.name, p.name))
        # All checks before the first rename: a refused target leaves ``out`` untouched.
        for item in items:
            target = out / item.name
            if target.is_symlink() or (target.exists() and target.is_dir() != item.is_dir()):
                raise UserError(
                    f"{target}: exists and is not this tool's output; move it away or "
                    "choose another --out"
                )
            if target.is_dir() and not (target / OUTPUT_MARK).is_file():
                raise UserError(
                    f"{target}: folder was not written by macromicro-sumo (no {OUTPUT_MARK}); "
                    "move it away or choose another --out"
                )
        # Manifests go last: a stage counts as done when its manifest exists, so a kill
        # between two renames must never leave a manifest beside missing files.
        for item in items:
            target = out / item.name
            if item.is_dir():
                mark_output(item)
            if target.is_dir():
                shutil.rmtree(target)
            os.replace(item, target)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
