"""Writing files atomically: readers never see a partial file, a crash never corrupts the old one."""
from __future__ import annotations

import contextlib
import os
import uuid
from typing import Iterator


def check_writable_folder(folder: str | os.PathLike, what: str = 'folder') -> None:
    """Create ``folder`` if needed and prove it writable with a probe file (permissions alone
    do not tell: a read-only mount or a root user). Raises OSError naming the folder."""
    folder = os.fspath(folder)
    try:
        os.makedirs(folder, exist_ok=True)
        probe = os.path.join(folder, f'.write-test.{uuid.uuid4().hex}')
        with open(probe, 'wb') as f:
            f.write(b'0')
        os.remove(probe)
    except OSError as e:
        raise OSError(e.errno, f'cannot write to this {what} ({e.strerror}): choose a '
                      f'writable place', folder) from None


def remove_stale_temporaries(folder: str | os.PathLike, name: str | None = None) -> list[str]:
    """Delete the temporary files that :func:`atomic_write_path` left for ``name`` (for every
    name when None) in ``folder`` when a process was killed mid-write. Returns the paths
    removed."""
    base, ext = os.path.splitext(name) if name is not None else ('', '')
    removed = []
    for entry in os.listdir(folder):
        if name is None:
            stale = entry.startswith('.') and '.tmp' in entry
        else:
            stale = entry.startswith(f'.{base}.') and entry.endswith(f'.tmp{ext}')
        if stale:
            path = os.path.join(folder, entry)
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
                removed.append(path)
    return removed


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
