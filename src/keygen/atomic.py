"""Atomic file writes: a reader (or a resumed run) sees the old file or the whole new one, never a torn one.

Every writer in KeyGen that a crash could interrupt (checkpoints, configs, stage records, caches, the
episode store's commit file) goes through :func:`atomic_write`: write a temporary sibling, then
``os.replace`` it onto the target. The temporary name keeps the target's suffix, so writers that add
one when it is missing (``numpy.savez``) write exactly the file they were given.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["atomic_write", "atomic_write_json", "atomic_write_text"]


def atomic_write(path: str | os.PathLike, write: Callable[[Path], Any], *, durable: bool = False) -> Path:
    """Call ``write(tmp)`` on a temporary sibling of ``path``, then rename it onto ``path``.

    ``durable=True`` also fsyncs the file and its directory, for files whose loss on power failure
    would lose data (not needed against a killed process, which the rename alone covers).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        if durable:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if durable:
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, *, durable: bool = False) -> Path:
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), durable=durable)


def atomic_write_json(path: str | os.PathLike, data: Any, *, indent: int | None = 2, **dumps: Any) -> Path:
    """``data`` as JSON (``default=str`` unless given), with a trailing newline."""
    dumps.setdefault("default", str)
    return atomic_write_text(path, json.dumps(data, indent=indent, **dumps) + "\n")
