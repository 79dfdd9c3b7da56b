"""Typed scenario fields: every field with a unit, an accepted range and a docstring.

A scenario file has one table per dataclass. Every field has a unit in its name
or docstring (``metadata["doc"]``) and, where it makes sense, an accepted range
(``metadata["range"]``, inclusive; ``None`` means unbounded). Loading rejects unknown
keys, missing required keys, wrong types and out-of-range values with a one-line
``UserError`` that names the file, the key and the accepted range.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import types
import typing
from dataclasses import field
from pathlib import Path
from typing import Any

from macromicro_sumo.errors import UserError

Pair = tuple[float, float]


def spec(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    doc: str = "",
    choices: tuple[str, ...] | None = None,
    accepted: str = "",
    omit_default: bool = False,
    omit_value: Any = dataclasses.MISSING,
    omit_unless: tuple[str, Any] | None = None,
) -> Any:
    """A dataclass field with its doc, accepted range and (for strings) choices.

    ``accepted``: the range as messages state it, where [lo, hi] cannot say it (an open end,
    checked by the scenario's own cross-field checks). ``omit_default``: ``to_dict`` leaves
    the field out while it has its default (a switch, off by default, whose key must not
    change the digest, checkpoints or recorded runs of the scenarios that do not set it).
    ``omit_value``: with ``omit_default``, the value left out instead of the default, for a
    field whose default moved: the value that does what the package did before the key
    existed. A scenario that does not set the key then records the new default, so a stage
    done under the old one is redone (``pipeline.schedule`` compares recorded keys), while
    one that sets the old value keeps its digest. ``omit_unless``: (sibling key, value):
    ``to_dict`` leaves the field out, whatever its value, where the sibling does not hold
    that value, for a key read only under it (nobody reads it elsewhere: it must not change
    the digest, nor redo a stage, of a scenario where it does nothing).
    """
    meta = {"range": (lo, hi), "doc": doc, "choices": choices, "accepted": accepted}
    if omit_default:
        meta["omit_default"] = True
        if omit_value is not dataclasses.MISSING:
            meta["omit_value"] = omit_value
    if omit_unless is not None:
        meta["omit_unless"] = omit_unless
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    if isinstance(default, list | dict):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


class ScenarioFile:
    """What every scenario kind does with the file it came from (``source``)."""

    source: str

    def resolve(self, relative: str) -> Path:
        """A path from the scenario file, relative to the file's folder."""
        p = Path(relative)
        return p if p.is_absolute() else (Path(self.source).parent / p).resolve()

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("source")
        _omit_defaults(self, d)
        # An absent optional table is left out: a scenario without one keeps its digest.
        return {k: v for k, v in d.items() if v is not None}

    def digest(self) -> str:
        """SHA-256 of the scenario as loaded (not of the file's bytes or comments)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()


def _omit_defaults(obj: Any, d: dict[str, Any]) -> None:
    """Drop from ``d`` (``obj`` as a dict) the ``omit_default`` fields at their default (or
    at their ``omit_value``, where the default moved) and the ``omit_unless`` fields whose
    sibling does not hold the value they are read under."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        unless = f.metadata.get("omit_unless")
        at_default = value == f.metadata.get("omit_value", f.default)
        unread = unless is not None and getattr(obj, unless[0]) != unless[1]
        if dataclasses.is_dataclass(value) and isinstance(d.get(f.name), dict):
            _omit_defaults(value, d[f.name])
        elif (f.metadata.get("omit_default") and at_default) or unread:
            d.pop(f.name, None)


def _describe_range(meta: dict[str, Any]) -> str:
    if meta.get("accepted"):
        return meta["accepted"]
    lo, hi = meta.get("range", (None, None))
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"[{lo_s}, {hi_s}]"


def _check_scalar(value: Any, kind: type, key: str, meta: dict[str, Any], file: str) -> Any:
    accepted = _describe_range(meta)
    if kind is bool:
        if not isinstance(value, bool):
            # A switch that also takes words (``bool | str``) names them all.
            raise UserError(
                f"{file}: {key} = {value!r} must be {meta.get('accepted') or 'true or false'}"
            )
        return value
    if kind is str:
        if not isinstance(value, str):
            raise UserError(f"{file}: {key} = {value!r} must be a string")
        choices = meta.get("choices")
        if choices and value not in choices:
            raise UserError(f"{file}: {key} = {value!r} is not accepted; accepted: {accepted}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise UserError(f"{file}: {key} = {value!r} must be a number in {accepted}")
    if kind is int and not float(value).is_integer():
        raise UserError(f"{file}: {key} = {value!r} must be an integer in {accepted}")
    value = kind(value)
    if not math.isfinite(value):
        raise UserError(f"{file}: {key} = {value!r} must be finite, in {accepted}")
    lo, hi = meta.get("range", (None, None))
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise UserError(f"{file}: {key} = {value!r} is out of range; accepted: {accepted}")
    return value


def table_class(hint: Any) -> Any:
    """The dataclass of a table field: ``Table``, or ``Table | None`` (an optional table,
    absent unless the file has it); None for any other field."""
    if dataclasses.is_dataclass(hint):
        return hint
    args = typing.get_args(hint)
    inner = [a for a in args if a is not type(None)]
    if len(args) == 2 and len(inner) == 1 and dataclasses.is_dataclass(inner[0]):
        return inner[0]
    return None


# Removed keys: a one-line error saying when and what replaces them, rather than "unknown
# key". Stop 25 removed the ring wing (issue 16); stop 32 two settings nothing read.
REMOVED_KEYS = {
    "evaluation.completions_per_scene": "stop 25: replaced by generator.eval_completions",
    "evaluation.min_safe_gap_m": "stop 32: never read; the leader-follower tests count a "
    "collision at a bumper gap of 0",
    "evaluation.timespace_s": "stop 32: never read; the time-space diagrams are drawn from "
    "the deployment's trajectories",
}


def build_table(cls: type, table: Any, prefix: str, file: str) -> Any:
    """``cls`` built from a TOML table, every key checked (one-line ``UserError`` otherwise)."""
    if not isinstance(table, dict):
        raise UserError(f"{file}: [{prefix}] must be a table")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls) if f.name != "source"}
    for key in table:
        dotted = f"{prefix}.{key}" if prefix else key
        if key not in known and dotted in REMOVED_KEYS:
            raise UserError(
                f"{file}: {dotted} was removed in {REMOVED_KEYS[dotted]}; remove the key"
            )
        if key not in known:
            where = f"[{prefix}] " if prefix else ""
            raise UserError(
                f"{file}: unknown key {where}{key!r}; accepted keys: {', '.join(sorted(known))}"
            )
    kwargs: dict[str, Any] = {}
    for name, f in known.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in table:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                hint = hints[name]
                what = f"table [{key}]" if dataclasses.is_dataclass(hint) else f"key {key!r}"
                raise UserError(f"{file}: missing required {what}")
            continue
        hint = hints[name]
        value = table[name]
        if (sub := table_class(hint)) is not None:
            kwargs[name] = build_table(sub, value, key, file)
        elif typing.get_origin(hint) is list:
            kind = typing.get_args(hint)[0]
            if not isinstance(value, list):
                raise UserError(f"{file}: {key} = {value!r} must be a list")
            kwargs[name] = [_check_scalar(v, kind, key, f.metadata, file) for v in value]
        elif typing.get_origin(hint) is tuple:
            kind = typing.get_args(hint)[0]
            if not isinstance(value, list) or len(value) != 2:
                raise UserError(
                    f"{file}: {key} = {value!r} must be a pair [low, high] in {_describe_range(f.metadata)}"
                )
            pair = tuple(_check_scalar(v, kind, key, f.metadata, file) for v in value)
            if pair[0] > pair[1]:
                raise UserError(
                    f"{file}: {key} = {value!r} is reversed; accepted [low, high] with "
                    f"low <= high, both in {_describe_range(f.metadata)}"
                )
            kwargs[name] = pair
        else:
            kind = hint if isinstance(hint, type) else typing.get_args(hint)[0]
            if isinstance(hint, types.UnionType):
                kind = typing.get_args(hint)[0]
                # A number or a word (``float | str``: a number in range or one of choices).
                if isinstance(value, str) and str in typing.get_args(hint):
                    kind = str
            kwargs[name] = _check_scalar(value, kind, key, f.metadata, file)
    return cls(**kwargs)
