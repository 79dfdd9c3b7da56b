"""Reading a SUMO net file for what neither libsumo nor sumolib gives (lane stopOffsets,
which edges reach a signal): the file opened gzip or plain, and each reader run once per
file and process, again where the file changed (its mtime or size)."""

from __future__ import annotations

import functools
import gzip
from collections.abc import Callable
from pathlib import Path
from typing import IO, TypeVar

T = TypeVar("T")


def open_net(net_file: str) -> IO[bytes]:
    """``net_file`` opened for binary reading, through gzip where it ends in ``.gz``."""
    return gzip.open(net_file, "rb") if net_file.endswith(".gz") else open(net_file, "rb")


def once_per_file(read: Callable[[str], T]) -> Callable[[Path], T]:
    """``read(net_file)`` cached per (path, mtime, size): a process reads each net once."""
    cached = functools.cache(lambda path, _mtime_ns, _size: read(path))

    @functools.wraps(read)
    def per_file(net_file: Path) -> T:
        st = Path(net_file).stat()
        return cached(str(net_file), st.st_mtime_ns, st.st_size)

    return per_file
