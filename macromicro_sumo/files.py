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

try:
    import fcntl
except ImportError:  # not on Windows: folders are then not locked
    fcntl = None  # type: ignore[assignment]
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from macromicro_sumo.errors import UserError

_UMASK = os.umask(0)
os.umask(_UMASK)


class WriteError(UserError):
    """An output could not be written (disk full, read-only folder): one line naming it."""

    def __init__(self, path: Path | str, exc: OSError) -> None:
        self.path, self.reason = Path(path), _reason(exc)
        super().__init__(f"{path}: cannot write ({self.reason})")


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it into place."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise WriteError(path, exc) from None
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs are ordinary files
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:  # disk full, read-only or vanished folder: one line, no traceback
        raise WriteError(path, exc) from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _reason(exc: OSError) -> str:
    """An OSError in words: 'No space left on device', 'Permission denied', ..."""
    return exc.strerror or str(exc) or type(exc).__name__


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
    return _scan(Path(path))[2]


# --------------------------------------------------------------------------- outputs map
#
# A stage's manifest records every file it wrote beside it: ``"outputs": {name: {"bytes",
# "sha256", "rows" (CSV data rows)}}``. A later stage reads those files through
# ``read_checked_csv`` / ``check_outputs``, so a truncated, edited or deleted output is a
# one-line error naming the file instead of a silently shorter dataset. Folders written
# before the map existed carry none and load unchecked.

MANIFEST = "manifest.json"


def _scan(path: Path) -> tuple[int, int, str]:
    """(bytes, lines, sha256) of ``path`` in one pass; a last line without newline counts."""
    h = hashlib.sha256()
    size = newlines = 0
    last = b""
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
            size += len(chunk)
            newlines += chunk.count(b"\n")
            last = chunk[-1:]
    return size, newlines + (1 if last not in (b"", b"\n") else 0), h.hexdigest()


def output_record(path: Path) -> dict[str, Any]:
    """What a manifest records of one output file: size, SHA-256, and CSV data rows."""
    size, lines, digest = _scan(path)
    record: dict[str, Any] = {"bytes": size, "sha256": digest}
    if path.suffix == ".csv":
        record["rows"] = max(lines - 1, 0)
    return record


def record_outputs(folder: Path, skip: Iterable[str] = (MANIFEST,)) -> dict[str, dict[str, Any]]:
    """The outputs map of every plain top-level file in ``folder`` but ``skip`` and hidden ones."""
    skip = set(skip)
    return {
        p.name: output_record(p)
        for p in sorted(folder.iterdir())
        if p.is_file() and not p.name.startswith(".") and p.name not in skip
    }


def write_manifest(manifest: dict[str, Any], folder: Path) -> None:
    """Write ``folder/manifest.json`` with the outputs map of the files already in ``folder``."""
    write_json({**manifest, "outputs": record_outputs(folder)}, folder / MANIFEST)


def write_stage_manifest(
    manifest: dict[str, Any], folder: Path, name: str, files: Iterable[str]
) -> None:
    """``folder/name`` with the outputs map of the stage's own ``files`` (those it wrote):
    a folder may hold several stages' outputs (the policy and its ablations)."""
    outputs = {f: output_record(folder / f) for f in files if (folder / f).is_file()}
    write_json({**manifest, "outputs": outputs}, folder / name)


def check_beside(path: Path | str, manifest_name: str) -> None:
    """Check ``path`` against the outputs map of the stage manifest beside it, if any: a
    checkpoint cut short or replaced since its stage wrote it is a one-line error."""
    path = Path(path)
    if path.is_file() and (path.parent / manifest_name).is_file():
        manifest = read_manifest(path.parent / manifest_name)
        check_outputs(path.parent, manifest, names=[path.name], manifest_name=manifest_name)


def read_manifest(path: Path | str) -> dict[str, Any]:
    """A stage's manifest as a dict; unreadable or not a JSON object is a one-line error."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: missing; re-run the stage that writes this folder") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(
            f"{path}: unreadable manifest ({type(exc).__name__}: {exc}); re-run the stage "
            "that writes this folder"
        ) from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: not a manifest (a JSON object); re-run the stage that wrote it")
    return data


def _rerun(manifest: dict[str, Any]) -> str:
    stage = str(manifest.get("stage") or "").replace("_", "-")
    return f"re-run `macromicro {stage}`" if stage else "re-run the stage that wrote it"


def check_outputs(
    folder: Path | str,
    manifest: dict[str, Any] | None = None,
    names: Iterable[str] | None = None,
    deep: bool = True,
    rerun: str = "",
    manifest_name: str = MANIFEST,
) -> None:
    """Check the files that ``folder``'s manifest lists (or ``names`` of them) against it.

    Missing files and other sizes or row counts are one-line errors naming the file;
    ``deep`` also compares SHA-256 (reads every byte). ``manifest``: the folder's manifest,
    already read (else ``folder/manifest.json``, when there is one). A manifest without an
    outputs map (written before it existed) checks nothing. ``rerun``: what the message
    tells the user to do (default: re-run the stage that wrote the folder).
    """
    folder = Path(folder)
    if manifest is None:
        if not (folder / MANIFEST).is_file():
            return
        manifest = read_manifest(folder / MANIFEST)
    outputs = manifest.get("outputs")
    if not isinstance(outputs, dict):
        return
    where = f"{manifest_name} of {folder}"
    hint = rerun or _rerun(manifest)
    for name in outputs if names is None else names:
        want = outputs.get(name)
        if not isinstance(want, dict):
            continue
        path = folder / name
        if not path.is_file():
            raise UserError(f"{path}: missing, though {where} lists it; {hint}")
        size = path.stat().st_size
        if not deep and size == want.get("bytes"):
            continue
        size, lines, digest = _scan(path)
        rows = max(lines - 1, 0)
        if "rows" in want and rows != want["rows"]:
            raise UserError(
                f"{path}: {rows} data rows, {where} records {want['rows']} (truncated or "
                f"edited); {hint}"
            )
        if size != want.get("bytes") or digest != want.get("sha256"):
            raise UserError(
                f"{path}: content differs from what {where} records ({size} bytes, recorded "
                f"{want.get('bytes')}; edited or corrupt); {hint}"
            )


def read_checked_csv(
    folder: Path | str,
    name: str,
    manifest: dict[str, Any] | None = None,
    columns: Iterable[str] = (),
    finite: Iterable[str] = (),
    **read_csv: Any,
) -> pd.DataFrame:
    """``folder/name`` as a DataFrame, checked against the folder's manifest (``check_outputs``),
    for ``columns`` and for finite numbers in the columns ``finite``; every problem is a
    one-line error naming the file (and the column and line)."""
    path = Path(folder) / name
    if not path.is_file():
        raise UserError(f"{path}: missing; {_rerun(manifest or {})}")
    check_outputs(folder, manifest, names=(name,))
    try:
        df = pd.read_csv(path, **read_csv)
    except ValueError as exc:  # pandas' parser and decoding errors are ValueErrors
        raise UserError(f"{path}: not a readable CSV ({type(exc).__name__}: {exc})") from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise UserError(f"{path}: missing column(s) {', '.join(missing)}")
    for col in finite:
        if col not in df.columns:
            continue
        values = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise UserError(
                f"{path}: column {col} holds {bad.size} value(s) that are not finite numbers, "
                f"first {df[col].iloc[bad[0]]!r} on line {bad[0] + 2}; accepted: finite numbers"
            )
    return df


# Every folder the tool writes carries this file. A folder is replaced only when it has it,
# so a user's own ``DIR/sumo`` (their network, say) is never deleted by ``--out DIR``.
OUTPUT_MARK = ".macromicro-output"


def mark_output(folder: Path) -> None:
    """Mark ``folder`` as written by this tool (it may be replaced by a later run)."""
    (folder / OUTPUT_MARK).write_text("written by macromicro-sumo; a later run may replace it\n")


def refuse_comma(path: Path | str, where: str) -> None:
    """SUMO splits every file option at commas (``-n a,b.net.xml`` opens ``a`` and
    ``b.net.xml``), with no way to quote one: refuse such a path before SUMO misreads it."""
    text = str(path)
    if "," in text:
        raise UserError(
            f"{where}: {text} has a comma, and SUMO splits its file lists at commas (it would "
            f"open {text.split(',')[0]!r}); rename or move it to a path without ','"
        )


def check_out_path(out: Path | str, inputs: Iterable[Path | str] = ()) -> None:
    """Refuse output folders that would put the user's files at risk, or SUMO would misread.

    ``/``, the home folder, an input file itself, or a folder holding an input: a stage
    replaces its output folders, so none of these may be one. A comma anywhere in the path:
    stages hand SUMO files inside ``out`` (``refuse_comma``).
    """
    where = Path(out).expanduser().resolve()
    refuse_comma(where, "--out")
    if where == Path(where.anchor) or where == Path.home().resolve():
        raise UserError(f"--out {out}: refusing the root or home folder; pass a folder of its own")
    for item in inputs:
        src = Path(item).expanduser().resolve()
        if src == where or where in src.parents:
            raise UserError(
                f"--out {out}: holds the input {item}; pass an output folder outside the inputs"
            )


# --------------------------------------------------------------------------- memory


def memory_limit_bytes() -> int | None:
    """Physical memory of this machine, or the container's (cgroup) limit where lower."""
    limits = []
    with contextlib.suppress(ValueError, OSError, AttributeError):
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    for cgroup in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        with contextlib.suppress(OSError):
            text = Path(cgroup).read_text().strip()
            if text.isdigit():
                limits.append(int(text))
    return min(limits) if limits else None


def _size(n_bytes: float) -> str:
    return f"{n_bytes / 2**40:,.1f} TiB" if n_bytes >= 2**40 else f"{n_bytes / 2**30:,.1f} GiB"


def check_memory(need_bytes: float, what: str, fix: str) -> None:
    """Refuse work whose estimated peak memory (``need_bytes``) exceeds this machine's."""
    have = memory_limit_bytes()
    if have is not None and need_bytes > have:
        raise UserError(
            f"{what} need about {_size(need_bytes)} of memory, more than the {_size(have)} of "
            f"this machine; {fix}"
        )


# --------------------------------------------------------------------------- one writer

STAGING_PREFIX = ".staging-"
_LOCKED: set[str] = set()  # output folders this process holds (``out_lock`` is re-entrant)


@contextlib.contextmanager
def out_lock(out: Path) -> Iterator[None]:
    """One writing process per output folder: a second is refused in one line.

    The lock is ``flock`` on the folder itself (no lock file is left behind) and dies with its
    process, even on SIGKILL. While it is held no other run stages into ``out``, so the
    ``.staging-*`` folders found there are those of a killed run: they are removed.
    """
    key = str(Path(out).resolve())
    if key in _LOCKED or fcntl is None:
        yield
        return
    fd = os.open(key, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(
                f"{out}: another macromicro run is writing into this folder; wait for it to "
                "finish or choose another --out"
            ) from None
        except OSError:
            pass  # a file system without flock (some network mounts): no lock
        for stale in Path(key).glob(f"{STAGING_PREFIX}*"):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
        _LOCKED.add(key)
        try:
            yield
        finally:
            _LOCKED.discard(key)
    finally:
        os.close(fd)  # releases the lock


def locked_by_caller(folders: Iterable[Path | str]) -> None:
    """Folders whose ``out_lock`` the process that started this one holds for as long as
    this one runs (a pipeline's stage in a worker process): this process writes into them
    without taking the lock again, which would be refused."""
    _LOCKED.update(str(Path(f).resolve()) for f in folders)


def prepare_out_dir(out: Path | str, inputs: Iterable[Path | str] = ()) -> Path:
    """Check that ``out`` can hold outputs: a folder or nothing yet, never a file."""
    check_out_path(out, inputs)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: output folder is an existing file; pass a folder path")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out}: cannot create output folder ({_reason(exc)})") from None
    try:  # an existing folder may be read-only (or on a read-only file system)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise UserError(
            f"{out}: output folder is not writable ({_reason(exc)}); pass a folder you can write"
        ) from None
    if _SESSIONS:  # held until the stage (or the whole run) ends
        _SESSIONS[-1].enter_context(out_lock(out))
    else:
        with out_lock(out):  # refuses a folder another run is writing; clears a killed run's
            pass
    return out


_SESSIONS: list[contextlib.ExitStack] = []


@contextlib.contextmanager
def writer_session() -> Iterator[None]:
    """Every output folder prepared inside stays locked until the block ends.

    A stage prepares its folder only once its inputs are known to be good (a refused input
    leaves no folder behind), so the lock is taken there and released here, when the stage
    or the whole pipeline has finished: a second run into the same ``--out`` is refused for
    all of that time, not only while a stage stages files.
    """
    with contextlib.ExitStack() as stack:
        _SESSIONS.append(stack)
        try:
            yield
        finally:
            _SESSIONS.pop()


@contextlib.contextmanager
def staging_dir(out: Path) -> Iterator[Path]:
    """A scratch folder inside ``out`` whose contents move into ``out`` only on success.

    Stages write many files; staging them keeps ``out`` free of partial results when a
    stage fails half-way (bad input found late, SUMO error, Ctrl-C). The stage holds
    ``out_lock`` meanwhile: a second run into ``out`` is refused, and a staging folder left
    by a killed run is removed.
    """
    with out_lock(out), _staged(out) as stage:
        yield stage


@contextlib.contextmanager
def _staged(out: Path) -> Iterator[Path]:
    try:
        stage = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out))
    except OSError as exc:
        raise UserError(f"{out}: cannot write into the output folder ({_reason(exc)})") from None
    try:
        try:
            yield stage
        except (OSError, WriteError) as exc:  # a write failed: disk full, permissions
            path = exc.path if isinstance(exc, WriteError) else Path(exc.filename or stage)
            reason = exc.reason if isinstance(exc, WriteError) else _reason(exc)
            if path == stage or stage in path.parents:
                # Named where it was going: the staging folder is gone with this error.
                path = out / path.relative_to(stage)
                raise UserError(f"{path}: cannot write ({reason}); {out} is unchanged") from None
            if isinstance(exc, WriteError):
                raise
            raise UserError(f"{path}: {reason}") from None
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
        try:
            for item in items:
                target = out / item.name
                if item.is_dir():
                    mark_output(item)
                if target.is_dir():
                    shutil.rmtree(target)
                os.replace(item, target)
        except OSError as exc:
            raise UserError(f"{exc.filename or out}: cannot replace ({_reason(exc)})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
