"""Torch checkpoints written atomically and read back with one-line errors.

A checkpoint is a dict with a ``format`` tag, the network's ``state_dict`` and
``hidden_size``, and the ``signature`` of the scenario values it is valid for: loading one
written for another scenario (or a corrupt file) is a UserError naming the file and what
differs, never a traceback.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from macromicro_sumo.errors import UserError
from macromicro_sumo.files import atomic_path


def save_torch(path: Path, payload: dict[str, Any]) -> None:
    """``torch.save`` to a temporary name, then rename: a crash never leaves half a file."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


def save_network(
    path: Path,
    fmt: str,
    net: nn.Module,
    signature: dict[str, Any],
    scenario: dict[str, Any],
    extra: dict[str, Any] | None = None,
) -> None:
    """The checkpoint ``load_network`` reads: format tag, weights, width, signature, scenario."""
    save_torch(
        path,
        {
            "format": fmt,
            "state_dict": net.state_dict(),
            "hidden_size": net.hidden_size,
            "signature": signature,
            "scenario": scenario,
            **(extra or {}),
        },
    )


def load_network(
    path: Path | str,
    fmt: str,
    what: str,
    signature: dict[str, Any],
    make: Callable[[int], nn.Module],
    source: str,
    before: dict[str, Any] | None = None,
) -> Any:
    """The network in ``path`` (``make(hidden_size)`` with its weights), in eval mode.

    ``what`` names the checkpoint in messages ("generator"); ``signature`` holds the
    scenario values the checkpoint must have been trained for; ``source`` the scenario file;
    ``before`` the values that signature keys added later had implicitly in older files.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {what} checkpoint not found (run `macromicro train-generator`)")
    corrupt = f"{path}: corrupt or truncated {what} checkpoint"
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise UserError(f"{corrupt} ({type(exc).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise UserError(
            f"{path}: not a {what} checkpoint (written by `macromicro train-generator`)"
        )
    try:
        trained_for = (before or {}) | dict(payload["signature"])
    except Exception as exc:  # a field missing or of the wrong shape
        raise UserError(f"{corrupt} ({type(exc).__name__})") from None
    # Before the weights: a key that changes the network's inputs changes their shapes.
    for key, want in signature.items():
        if trained_for.get(key) != want:
            raise UserError(
                f"{path}: {what} was trained for {key} = {trained_for.get(key)}, "
                f"scenario {source} has {want}"
            )
    try:
        net = make(int(payload["hidden_size"]))
        net.load_state_dict(payload["state_dict"])
    except Exception as exc:  # a field missing or of the wrong shape
        raise UserError(f"{corrupt} ({type(exc).__name__})") from None
    net.eval()
    return net
