"""Files appear whole or not at all: every output is written to a temporary name beside it, then renamed.

A crash, a full disk or Ctrl-C then leaves either the previous file or nothing, never a truncated table, weights
file or trajectory that a later run would read as valid. The rename (`os.replace`) is atomic on POSIX.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write `path`'s content to; it becomes `path` only if the block succeeds.

    The temporary name keeps the suffix (``.x.1234.tmp.png``) because savefig, imwrite and np.save choose the
    format from it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write(path: str | Path, data: str | bytes) -> Path:
    """Write text or bytes to `path` atomically."""
    with atomic_path(path) as tmp:
        if isinstance(data, bytes):
            tmp.write_bytes(data)
        else:
            tmp.write_text(data)
    return Path(path)
