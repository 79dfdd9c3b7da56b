"""A batch's variants: scenario files, globs, and the ``[sweep]`` table of a scenario,
expanded into the cartesian product of named variants::

    [sweep]
    seed = [1, 2, 3]
    speed_limits.range_mps = [[10.0, 12.0], [12.0, 14.0]]   # dotted key: table.key
    n_runs = [10, 40]                                       # short key: unique across tables

Sweep keys are those of the file's kind: a section's (``[network] kind = "sumo"``:
``detectors.auto_spacing_m``, ``instrumented.penetration``, ...), the optional tables'
included where the file has them (a section's ``[fleet]``, ``[speed_limits]``, ``[initial]``:
``fleet.n_vehicles``; ``file_keys``); or a ring file's (its tables' section keys and the ring's
own, ``scenario.ring_as_section.RING_FILE_KEYS``), applied before the file is mapped.
"""

from __future__ import annotations

import dataclasses
import difflib
import glob
import hashlib
import itertools
import re
import typing
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError
from macromicro_sumo.scenario.fields import table_class
from macromicro_sumo.scenario.load import load_scenario, read_scenario_toml
from macromicro_sumo.scenario.ring_as_section import RING_FILE_KEYS, RING_TOP
from macromicro_sumo.scenario.section import SectionScenario

AnyScenario = SectionScenario
MAX_NAME = 120  # characters; longer variant names are shortened with a hash


def _leaf_keys(cls: type = SectionScenario, prefix: str = "") -> dict[str, Any]:
    """Every settable scenario key, dotted, mapped to its type hint (an optional table's
    keys too: sweeping ``fleet.n_vehicles`` sets a key of ``[fleet]``, not the table)."""
    out: dict[str, Any] = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name == "source":
            continue
        key = f"{prefix}{f.name}"
        if (table := table_class(hints[f.name])) is not None:
            out.update(_leaf_keys(table, key + "."))
        elif key != "network.kind":  # the kind picks the tables: one file per kind
            out[key] = hints[f.name]
    return out


# Sweepable keys per scenario kind, with an example for error messages.
_SECTION_KEYS = _leaf_keys(SectionScenario)
LEAF_KEYS: dict[str, dict[str, Any]] = {
    "ring": {
        **{
            k: v
            for k, v in _SECTION_KEYS.items()
            if k.split(".")[0] in RING_TOP and not k.startswith("network.")
        },
        **RING_FILE_KEYS,
    },
    "section": _SECTION_KEYS,
}
EXAMPLE_KEY = {"ring": "fleet.n_vehicles", "section": "detectors.auto_spacing_m"}
# Tables a file may leave out (``X | None``): their keys are sweepable only in a file that
# has the table, and only there count for short keys (``file_keys``).
OPTIONAL_TABLES: dict[str, set[str]] = {
    "ring": set(),  # a ring file has all its tables ([fleet] is its demand)
    "section": {
        f.name
        for f in dataclasses.fields(SectionScenario)
        if not dataclasses.is_dataclass(typing.get_type_hints(SectionScenario)[f.name])
        and table_class(typing.get_type_hints(SectionScenario)[f.name]) is not None
    },
}


def _tables(keys: dict[str, Any]) -> list[str]:
    return list(dict.fromkeys(k.split(".")[0] for k in keys if "." in k))


def _top_keys(keys: dict[str, Any]) -> list[str]:
    return [k for k in keys if "." not in k]


def file_keys(kind: str, tables: Collection[str] | None = None) -> dict[str, Any]:
    """The sweepable keys of a ``kind`` file with the top-level ``tables`` (None: any): an
    optional table's keys only where the file has that table (a section's [fleet] is its
    demand: a variant cannot add one to a file whose demand is its route files)."""
    if tables is None:
        return LEAF_KEYS[kind]
    absent = OPTIONAL_TABLES[kind] - set(tables)
    return {k: v for k, v in LEAF_KEYS[kind].items() if k.split(".")[0] not in absent}


def sweep_kind(table: dict[str, Any]) -> str | None:
    """The scenario kind of a raw scenario table (None when its network.kind is not valid)."""
    network = table.get("network")
    kind = network.get("kind", "ring") if isinstance(network, dict) else "ring"
    return {"ring": "ring", "sumo": "section"}.get(kind) if isinstance(kind, str) else None


def _flatten(table: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    # TOML reads ``fleet.n_vehicles = [...]`` as a nested table: undo that.
    for key, value in table.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def resolve_key(
    key: str, file: str, kind: str = "ring", tables: Collection[str] | None = None
) -> str:
    """The dotted key of a ``kind`` scenario a sweep key names (short keys must be unique
    across tables); ``tables``: the file's own (``file_keys``)."""
    keys = file_keys(kind, tables)
    if key in keys:
        return key
    if key == "network.kind":
        raise UserError(
            f"{file}: sweep key 'network.kind' cannot be swept; write one scenario file per kind"
        )
    if key in _tables(keys):
        example = next(k for k in keys if k.startswith(key + "."))
        raise UserError(
            f"{file}: sweep key {key!r} is a table; sweep one of its keys, e.g. {example}"
        )
    matches = [k for k in keys if k.rsplit(".", 1)[-1] == key]
    if len(matches) == 1:
        return matches[0]
    if len(matches) > 1:
        raise UserError(
            f"{file}: sweep key {key!r} is ambiguous; give one of {', '.join(sorted(matches))}"
        )
    close = difflib.get_close_matches(key, list(keys), n=3)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    what = "a section scenario" if kind == "section" else "a ring scenario"
    table = key.split(".")[0] if "." in key else ""
    if table in _tables(keys):  # a table of the file: name its keys
        own = ", ".join(k for k in keys if k.startswith(table + "."))
        raise UserError(
            f"{file}: unknown sweep key {key!r} for {what}; accepted keys of [{table}]: {own}{hint}"
        )
    missing = sorted(OPTIONAL_TABLES[kind] - set(_tables(keys)))
    optional = f" ({', '.join(f'[{t}]' for t in missing)} only in a file that has them)"
    optional = optional if missing else ""
    top, names = ", ".join(_top_keys(keys)), ", ".join(_tables(keys))
    raise UserError(
        f"{file}: unknown sweep key {key!r} for {what}; accepted: {top} or a dotted key "
        f"table.key of the tables {names}{optional} (e.g. {EXAMPLE_KEY[kind]}), or a key "
        f"name unique across tables{hint}"
    )


def parse_sweep(
    sweep: Any, file: str, kind: str = "ring", tables: Collection[str] | None = None
) -> list[tuple[str, str, list[Any]]]:
    """Validate a ``[sweep]`` table of a ``kind`` scenario (``"ring"`` or ``"section"``):
    (key as written, dotted key, values) in file order. ``tables``: the file's own tables
    (``resolve_key``)."""
    if not isinstance(sweep, dict) or not sweep:
        raise UserError(f"{file}: [sweep] must be a table of key = [value, ...] lines")
    out, seen = [], {}
    for key, values in _flatten(sweep):
        dotted = resolve_key(key, file, kind, tables)
        if dotted in seen:
            raise UserError(f"{file}: sweep keys {seen[dotted]!r} and {key!r} both set {dotted}")
        seen[dotted] = key
        if not isinstance(values, list) or not values:
            raise UserError(f"{file}: sweep.{key} = {values!r} must be a non-empty list of values")
        origin = typing.get_origin(LEAF_KEYS[kind][dotted])
        if origin in (tuple, list):
            what = "a pair [low, high]" if origin is tuple else "a list"
            for v in values:
                if not isinstance(v, list):
                    raise UserError(
                        f"{file}: sweep.{key} = {values!r}: each value must be {what}, "
                        f"e.g. [{values!r}] for one variant"
                    )
        out.append((key, dotted, values))
    return out


def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() else repr(value)
    if isinstance(value, list | tuple):
        return "_".join(_fmt(v) for v in value)
    return str(value)


def variant_name(parts: Sequence[tuple[str, Any]], prefix: str = "") -> str:
    """A deterministic, filesystem-safe name: ``seed=1__range_mps=12_14``."""
    words = ([prefix] if prefix else []) + [f"{k}={_fmt(v)}" for k, v in parts]
    name = re.sub(r"[^A-Za-z0-9._=+-]", "_", "__".join(words)).lstrip(".") or "variant"
    if len(name) > MAX_NAME:
        digest = hashlib.sha256(name.encode()).hexdigest()[:10]
        name = f"{name[: MAX_NAME - 11]}-{digest}"
    return name


@dataclass(frozen=True)
class Variant:
    """One scenario to run: a file, the sweep values applied to it, or why it cannot run."""

    name: str
    file: str
    params: dict[str, Any]  # dotted scenario key -> value
    scenario: AnyScenario | None
    error: str = ""

    @property
    def scenario_name(self) -> str:
        return self.scenario.name if self.scenario else ""


def expand_file(path: Path, prefix: str) -> list[Variant]:
    """The variants of one scenario file (one, unless it has a ``[sweep]`` table).

    A file that cannot be read gives one failed variant; a variant whose values fail
    validation is failed on its own. A malformed sweep is an error for the whole batch.
    """
    file = str(path)
    try:
        table, sweep = read_scenario_toml(path)
    except UserError as exc:
        return [Variant(prefix or path.stem, file, {}, None, str(exc))]
    kind = sweep_kind(table)
    if sweep is None or kind is None:  # an unaccepted network.kind fails in load_scenario
        return [_load(prefix or path.stem, path, {})]
    keys = parse_sweep(sweep, file, kind, list(table))
    out = []
    for combo in itertools.product(*(values for _, _, values in keys)):
        parts = [(key, v) for (key, _, _), v in zip(keys, combo, strict=True)]
        params = {dotted: v for (_, dotted, _), v in zip(keys, combo, strict=True)}
        out.append(_load(variant_name(parts, prefix), path, params))
    _refuse_identical(out, file)
    return out


def _refuse_identical(variants: Sequence[Variant], file: str) -> None:
    """Two variants that load to the same scenario would run the same thing twice and read
    as a sensitivity of zero: a swept key that this scenario never reads (say, a ring key
    that its section mapping drops)."""
    seen: dict[str, Variant] = {}
    for v in variants:
        if v.scenario is None:
            continue
        d = v.scenario.digest()
        if d in seen:
            first = seen[d]
            keys = sorted(k for k in v.params if v.params[k] != first.params.get(k))
            raise UserError(
                f"{file}: [sweep] variants {first.name!r} and {v.name!r} load to the same "
                f"scenario: {', '.join(keys)} has no effect on this scenario; sweep another key"
            )
        seen[d] = v


def _load(name: str, path: Path, params: dict[str, Any]) -> Variant:
    try:
        return Variant(name, str(path), params, load_scenario(path, params, allow_sweep=True))
    except UserError as exc:
        return Variant(name, str(path), params, None, str(exc))


def resolve_inputs(inputs: Sequence[str | Path]) -> list[Path]:
    """Scenario files from paths and globs, in the given order, without duplicates."""
    files: list[Path] = []
    for item in inputs:
        s = str(item)
        if Path(s).is_file():
            found = [Path(s)]
        elif glob.has_magic(s):
            found = [Path(p) for p in sorted(glob.glob(s, recursive=True)) if Path(p).is_file()]
            if not found:
                raise UserError(f"{s}: no scenario file matches this pattern")
        elif Path(s).is_dir():
            raise UserError(f"{s}: is a folder; pass scenario files or a glob such as '{s}/*.toml'")
        else:
            raise UserError(f"{s}: scenario file not found")
        for p in found:
            if p.resolve() not in {f.resolve() for f in files}:
                files.append(p)
    return files


def expand(inputs: Sequence[str | Path]) -> list[Variant]:
    """Every variant of every input; names are prefixed by the file stem when several files."""
    files = resolve_inputs(inputs)
    stems: dict[str, Path] = {}
    for f in files:
        if f.stem in stems:
            raise UserError(
                f"{f}: has the same name as {stems[f.stem]}; variant folders are named after "
                "files, so rename one"
            )
        stems[f.stem] = f
    variants = [v for f in files for v in expand_file(f, f.stem if len(files) > 1 else "")]
    names: dict[str, Variant] = {}
    for v in variants:
        if v.name in names:
            raise UserError(
                f"{v.file}: sweep values {names[v.name].params} and {v.params} give the same "
                f"variant name {v.name!r}; make the values distinct"
            )
        names[v.name] = v
    return variants
