"""Writing files atomically: readers never see a partial file, a crash never corrupts the old one."""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import socket
import stat
import sys
import time
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


def is_utf8(path: str | os.PathLike) -> bool:
    """Whether ``path`` is valid UTF-8 text: what libraries that take a path as ``str`` and
    hand it to C++ (OpenEXR, Mitsuba, USD) accept. A Linux name may be any bytes but ``/``
    and NUL; Python gives one that is not UTF-8 as a ``str`` with surrogate escapes
    (``os.fsdecode``), which those libraries refuse."""
    try:
        os.fsencode(path).decode('utf-8')
    except UnicodeDecodeError:
        return False
    return True


def as_text(name: str) -> str:
    """``name`` (a path or a file's name, :func:`is_utf8` or not) as text that any format
    holding text takes (USD, JSON read by other tools, a page): its bytes read as UTF-8, each
    byte that is not UTF-8 written ``\\xNN`` (as Python prints bytes). A UTF-8 name is itself;
    its exact bytes are :func:`name_bytes`. None (no name) stays None."""
    return None if name is None else os.fsencode(name).decode('utf-8', 'backslashreplace')


def name_bytes(name: str) -> str | None:
    """The bytes of a ``name`` that is not UTF-8, in hexadecimal (kept beside
    :func:`as_text` where a format has room); None for a UTF-8 name (or none)."""
    return None if name is None or is_utf8(name) else os.fsencode(name).hex()


def _as_text_tree(data):
    """``data`` (JSON-ready) with every text :func:`as_text`."""
    if isinstance(data, str):
        return as_text(data)
    if isinstance(data, dict):
        return {as_text(k) if isinstance(k, str) else k: _as_text_tree(v)
                for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_as_text_tree(v) for v in data]
    return data


def _ascii_name(name: str) -> str:
    """``name`` with every byte outside printable ASCII (and a space) as ``_``: the part of a
    temporary file's name taken from the file it stands for."""
    return ''.join(chr(b) if 0x20 < b < 0x7f else '_' for b in os.fsencode(name))


def _temporary_name(base: str, ext: str, unique: str) -> str:
    return f'.{_ascii_name(base)}.{unique}.tmp{_ascii_name(ext)}'


@contextlib.contextmanager
def folder_path(folder: str | os.PathLike) -> Iterator[str]:
    """Yield a UTF-8 path of ``folder`` for the time of the ``with``: ``folder`` itself when it
    is UTF-8, else ``/proc/self/fd/N`` of a descriptor of the folder (Linux), which names the
    same folder in ASCII. Names in it made of UTF-8 may be joined to it."""
    folder = os.fsdecode(folder)
    if is_utf8(folder) or not os.path.isdir('/proc/self/fd'):
        yield folder
        return
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        yield f'/proc/self/fd/{fd}'
    finally:
        os.close(fd)


@contextlib.contextmanager
def readable_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a UTF-8 path that reads the file ``path`` for the time of the ``with``, for the
    libraries that refuse a name of other bytes (see :func:`is_utf8`): ``path`` itself when
    it is UTF-8, else its name in :func:`folder_path` of its folder, else (a name that is not
    UTF-8 itself) ``/proc/self/fd/N`` of a descriptor of the file. A missing file is left to
    the reader to report."""
    path = os.fsdecode(path)
    if is_utf8(path) or not os.path.isdir('/proc/self/fd'):
        yield path
        return
    folder, name = os.path.split(os.path.abspath(path))
    if is_utf8(name):
        with folder_path(folder) as safe:
            yield os.path.join(safe, name)
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        yield f'/proc/self/fd/{fd}'
    finally:
        os.close(fd)


def remove_stale_temporaries(folder: str | os.PathLike, name: str | None = None) -> list[str]:
    """Delete the temporary files that :func:`atomic_write_path` left for ``name`` (for every
    name when None) in ``folder`` when a process was killed mid-write. Returns the paths
    removed."""
    base, ext = os.path.splitext(name) if name is not None else ('', '')
    prefix, suffix = f'.{_ascii_name(base)}.', f'.tmp{_ascii_name(ext)}'
    removed = []
    for entry in os.listdir(folder):
        if name is None:
            stale = entry.startswith('.') and '.tmp' in entry
        else:
            stale = entry.startswith(prefix) and entry.endswith(suffix)
        if stale:
            path = os.path.join(folder, entry)
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
                removed.append(path)
    return removed


@contextlib.contextmanager
def atomic_write_path(path: str | os.PathLike, utf8: bool = True) -> Iterator[str]:
    """Yield a temporary path next to ``path``; move it onto ``path`` on success.

    The parent directory is created if needed. Readers never see a partially
    written file, and on error the temporary file is removed; an operating-system error that
    names no file (a full disk while writing) is given ``path``. The temporary path is UTF-8
    whatever ``path`` is (its name ASCII, its folder :func:`folder_path`), so that the
    libraries that refuse other bytes (OpenEXR, Mitsuba, USD) write it; the move onto
    ``path`` takes any name. ``utf8=False`` yields the temporary file's own path in the folder
    as it is named, for a writer in another process (ffmpeg), which takes any bytes but not
    this process's ``/proc/self/fd`` descriptors.
    """
    path = os.fsdecode(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    base, ext = os.path.splitext(os.path.basename(path))
    # A fresh unique name rather than mkstemp, so the writer creates the file
    # with the usual umask permissions instead of mkstemp's 0600.
    name = _temporary_name(base, ext, uuid.uuid4().hex)
    tmp = os.path.join(directory, name)
    try:
        if utf8:
            with folder_path(directory) as safe:
                yield os.path.join(safe, name)
        else:
            yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        if isinstance(e, OSError) and e.errno is not None and not e.filename:
            e.filename = path           # (an error of the system's, not one raised by hand)
        raise


# ----------------------------------------------------------------------------- folder locks

LOCK_NAME = '.mi-nerfpp.lock'
# The folder locks this process holds: (process id, real path) -> [descriptor, holders]. A
# process may lock a folder it holds again (a run prepared, then resumed in the same
# process); the lock goes when its last holder releases it.
_HELD: dict = {}


class FolderInUseError(RuntimeError):
    """Another live process holds the folder's lock."""


class FolderLock:
    """An exclusive lock on a folder, held by this process until :meth:`release` (or its
    exit; a process may take a lock it holds again, released with its last holder):
    ``fcntl.flock`` on the file :data:`LOCK_NAME` in the folder, which names the
    holder (process id, host, command). The operating system releases the lock of a process
    that dies, however it dies, so a lock is never left stale by a killed run; the file
    stays. Where the file system has no ``flock`` the file itself is the lock: one naming a
    process of this host that is no longer running is stale and taken over."""

    def __init__(self, folder, key):
        self.folder, self._key = folder, key

    @property
    def path(self):
        return os.path.join(self.folder, LOCK_NAME)

    def release(self):
        key, self._key = self._key, None
        held = _HELD.get(key) if key is not None else None
        if held is not None:
            held[1] -= 1
            if held[1] <= 0:
                del _HELD[key]
                os.close(held[0])     # closing the descriptor releases the flock

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def _holder_text():
    command = ' '.join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))
    return (f'pid {os.getpid()} on {socket.gethostname()} since '
            f'{time.strftime("%Y-%m-%d %H:%M:%S")}: {command}'[:500])


def _holder_pid(text):
    """(pid, host) of a lock file's text, or None."""
    m = re.match(r'pid (\d+) on (\S+) ', text)
    return (int(m.group(1)), m.group(2)) if m else None


def lock_folder(folder, what: str = 'folder') -> FolderLock:
    """Take the exclusive lock of ``folder`` (created if needed), or raise
    :class:`FolderInUseError` naming the process that holds it."""
    folder = os.fspath(folder)
    os.makedirs(folder, exist_ok=True)
    key = (os.getpid(), os.path.realpath(folder))
    if key in _HELD:                     # held by this process already: one more holder
        _HELD[key][1] += 1
        return FolderLock(folder, key)
    path = os.path.join(folder, LOCK_NAME)
    try:
        # Never through a link: a lock file that links to a user's file would overwrite it.
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as e:
        if e.errno == errno.EISDIR:
            raise ValueError(f'{path!r}: the lock file of this {what} is a folder: remove it '
                             f'and run again') from None
        if e.errno != errno.ELOOP:
            raise
        raise ValueError(
            f'{path!r}: the lock file of this {what} is a symbolic link (to '
            f'{os.readlink(path)!r}); mi-nerfpp does not write through it: remove the link and '
            f'run again') from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise ValueError(f'{path!r}: the lock file of this {what} is not a regular file: '
                               f'remove it and run again')
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise FolderInUseError(f'{folder}: this {what} is in use by another mi-nerfpp '
                                       f'process ({_read_text(fd) or "unknown"}); wait for it '
                                       f'to end or stop it, or choose another one') from None
            if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                raise
            holder = _holder_pid(_read_text(fd))         # no flock here: the file is the lock
            if holder and holder[1] == socket.gethostname() and holder[0] != os.getpid() \
                    and _alive(holder[0]):
                raise FolderInUseError(f'{folder}: this {what} is in use by another mi-nerfpp '
                                       f'process ({_read_text(fd)}); wait for it to end or '
                                       f'stop it, or choose another one') from None
        os.ftruncate(fd, 0)
        # The command's arguments as the system gave them: a path of non-UTF-8 bytes is a str
        # with surrogate escapes, written back as its bytes.
        os.pwrite(fd, (_holder_text() + '\n').encode(errors='surrogateescape'), 0)
    except BaseException:
        os.close(fd)
        raise
    _HELD[key] = [fd, 1]
    return FolderLock(folder, key)


def _read_text(fd):
    try:
        return os.pread(fd, 1000, 0).decode(errors='surrogateescape').strip()
    except OSError:
        return ''


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_entries(folder, names) -> None:
    """Remove the files and folders ``names`` of ``folder`` that exist (an earlier output)."""
    for name in names:
        path = os.path.join(folder, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        elif os.path.lexists(path):
            os.remove(path)


def check_not_a_file(folder, option: str = '--out'):
    """Refuse a ``folder`` to write into that is an existing file (ValueError naming the
    option), before anything is written."""
    folder = os.fspath(folder)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f'{option} {folder} is an existing file, not a folder: choose '
                         f'another {option}')


def write_json(path, data, text=False):
    """Write ``data`` as indented JSON to ``path``, atomically. ``text``: a file for other
    tools (metrics, a sweep's table), whose names and paths are written :func:`as_text` (JSON
    from Python keeps a name that is not UTF-8 as lone surrogates ``\\udcNN``, which Python
    reads back to the same bytes and stricter readers refuse)."""
    data = _as_text_tree(data) if text else data
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        json.dump(data, f, indent=2)
