"""Writing files atomically: readers never see a partial file, a crash never corrupts the old one."""
from __future__ import annotations

import contextlib
import os
import uuid
from typing import Iterator


@contextlib.contextmanager
def atomic_write_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path next to ``path``; move it onto ``path`` on success.

    The parent directory is created if needed. Readers never see a partially
    written file, and on error the temporary file is removed.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    base, ext = os.path.splitext(os.path.basename(path))
    # A fresh unique name rather than mkstemp, so the writer creates the file
    # with the usual umask permissions instead of mkstemp's 0600.
    tmp = os.path.join(directory, f'.{base}.{uuid.uuid4().hex}.tmp{ext}')
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise
