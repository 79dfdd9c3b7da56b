"""Progress of long stages: a live bar on a terminal, one line per stage otherwise.

A log file (``make run > log``, CI, a batch worker's stderr) gets a single summary line
when a stage ends instead of every bar refresh.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

from tqdm import tqdm as _tqdm


class _StageLine:
    """tqdm's interface (iterate, update, set_postfix, write, close), printing one line."""

    def __init__(
        self,
        iterable: Iterable[Any] | None = None,
        total: int | None = None,
        desc: str = "",
        unit: str = "it",
        disable: bool = False,
        **_: Any,
    ) -> None:
        self.iterable, self.desc, self.unit, self.disable = iterable, desc, unit, disable
        self.total = total if total is not None else _length(iterable)
        self.n, self.postfix, self.t0, self.closed = 0, "", time.perf_counter(), False

    def __iter__(self) -> Iterator[Any]:
        assert self.iterable is not None
        try:
            for item in self.iterable:
                yield item
                self.n += 1
        finally:
            self.close()

    def __enter__(self) -> _StageLine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_postfix(self, **kwargs: Any) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in kwargs.items())

    def write(self, text: str) -> None:
        if not self.disable:
            print(text, file=sys.stderr)

    def close(self) -> None:
        if self.closed or self.disable:
            self.closed = True
            return
        self.closed = True
        of = f"/{self.total}" if self.total is not None else ""
        tail = f" ({self.postfix})" if self.postfix else ""
        wall = time.perf_counter() - self.t0
        print(f"{self.desc}: {self.n}{of} {self.unit} in {wall:.1f} s{tail}", file=sys.stderr)


def _length(iterable: Iterable[Any] | None) -> int | None:
    try:
        return len(iterable)  # type: ignore[arg-type]
    except TypeError:
        return None


def tqdm(*args: Any, **kwargs: Any) -> Any:
    """A progress bar: ``tqdm.tqdm`` on a terminal, else one summary line at the end."""
    if sys.stderr.isatty():
        return _tqdm(*args, **kwargs)
    return _StageLine(*args, **kwargs)
