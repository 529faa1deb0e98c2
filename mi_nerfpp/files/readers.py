"""Reading the JSON, NumPy, EXR and image files the package keeps or is given, one reader per
kind of file: a missing, unreadable, empty, damaged or wrong-type file ends with one line that
names the file, says what is wrong with it and what to do.

* :func:`read_json` (a file) and :func:`decode_json` (JSON text kept inside another file, a
  checkpoint's config) return the decoded value, checked to be of the type the caller expects;
* :func:`read_npz` returns the arrays of an ``.npz`` archive (all, or the ones asked for), and
  :func:`read_npy` the array of an ``.npy`` file, never unpickling anything;
* :func:`read_exr` returns the header and channels of an OpenEXR file (deep ones included), and
  :func:`read_image` the pixels of a PNG or JPEG file, as imageio gives them;
* :func:`open_photo` opens a photo of any format Pillow reads (JPEG, PNG, TIFF, ...) as a
  Pillow image, for what needs more than its pixels: its EXIF, turning it upright, a crop.

Every error is the caller's ``error`` class (:class:`FileReadError` unless the caller names its
own: ``DatasetError``, ``CameraPathError``, ...), a ``ValueError`` whose one line is
``<file>: cannot read <what> (<what is wrong>): <what to do>``; ``what`` and the remedy are the
caller's (``"delete the folder X to rebuild it"``, ``"export the dataset again"``). The error
carries the parts as attributes (``path``, ``detail``, ``remedy``), for a caller that keeps its
own wording (the checkpoint reader's). Every JSON and NumPy read of the package goes through
here (``tests/files/test_readers.py`` finds any other); EXR files and images are read here or
by :mod:`mi_nerfpp.files.exr` (multi-layer renders) and :mod:`mi_nerfpp.data.images` (dataset
images, as float RGB).
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import sys
import zipfile
from typing import Any, Iterable, NoReturn

import imageio.v3 as iio
import numpy as np
import OpenEXR

from mi_nerfpp.files.atomic import readable_path

FIX = 'fix or replace the file'
_NPY_MAGIC = b'\x93NUMPY'
_ZIP_MAGIC = b'PK'


class FileReadError(ValueError):
    """A file that cannot be read: missing, not a file, unreadable, empty, damaged or holding
    the wrong kind of value. Its message is one line: the file, what is wrong with it, what to
    do."""


def _fail(error: type[Exception], path: str, what: str, detail: str,
          remedy: str | None) -> NoReturn:
    message = f'{path}: cannot read {what} ({detail})' + (f': {remedy}' if remedy else '')
    exc = error(message)
    exc.path, exc.detail, exc.remedy = path, detail, remedy
    raise exc from None


def _name(path) -> str:
    return os.fsdecode(os.fspath(path))


def _read_bytes(path: str, what: str, remedy: str | None, error, size: int = -1) -> bytes:
    """The bytes of ``path`` (its first ``size``, or all), or ``error`` for a file that is
    missing, a folder, unreadable or empty."""
    try:
        with open(path, 'rb') as f:
            data = f.read(size)
    except FileNotFoundError:
        _fail(error, path, what, 'not found', remedy)
    except IsADirectoryError:
        _fail(error, path, what, 'a folder, not a file', remedy)
    except OSError as e:
        _fail(error, path, what, e.strerror or type(e).__name__, remedy)
    if not data:
        _fail(error, path, what, 'the file is empty, 0 bytes', remedy)
    return data


# ------------------------------------------------------------------------------------- JSON

_JSON_NAMES = {dict: 'an object', list: 'an array', str: 'a string', bool: 'true or false',
               int: 'a number', float: 'a number', type(None): 'null'}


def _kinds(expect) -> tuple:
    return expect if isinstance(expect, tuple) else (expect,)


def _matches(value, expect) -> bool:
    """Whether ``value`` is of a type of ``expect`` (``true`` is not a number here)."""
    if isinstance(value, bool):
        return bool in _kinds(expect)
    return isinstance(value, expect)


def _json_type(value) -> str:
    return next(name for kind, name in _JSON_NAMES.items() if type(value) is kind)


def _expected(expect) -> str:
    return ' or '.join(dict.fromkeys(_JSON_NAMES.get(k, k.__name__) for k in _kinds(expect)))


def read_json(path, what: str = 'JSON file', remedy: str | None = FIX, expect=dict,
              error: type[Exception] = FileReadError) -> Any:
    """The value of the JSON file ``path``.

    Args:
        what: what the file is, after "cannot read" (``'camera path file'``).
        remedy: what to do about a file that cannot be read (``'delete the folder X to
            rebuild it'``); None: nothing said.
        expect: the type (or tuple of types) the top-level value must have (``dict``: an
            object, ``list``: an array); None: any.
        error: the exception class raised, with the message as its one argument.

    Raises:
        error: the file is missing, a folder, unreadable, empty, not UTF-8, not valid or
            complete JSON, or holds a value of another type than ``expect``.
    """
    path = _name(path)
    return decode_json(_read_bytes(path, what, remedy, error), path, what, remedy, expect, error)


def decode_json(text: str | bytes, source, what: str = 'JSON', remedy: str | None = FIX,
                expect=dict, error: type[Exception] = FileReadError) -> Any:
    """The value of the JSON ``text`` read from ``source`` (the file it was read from, named in
    the error), checked as :func:`read_json` checks a file's."""
    source = _name(source)
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode('utf-8-sig')
        except UnicodeDecodeError as e:
            _fail(error, source, what, f'not UTF-8 text: byte 0x{e.object[e.start]:02x} at '
                                       f'offset {e.start}', remedy)
    if not text.strip():
        _fail(error, source, what, 'no JSON in it, only white space' if text else 'empty',
              remedy)
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        cut = e.pos >= len(text.rstrip()) or e.msg.startswith('Unterminated string')
        where = f'line {e.lineno} column {e.colno}'
        _fail(error, source, what, f'the JSON is cut short at {where}' if cut else
              f'invalid JSON at {where}: {e.msg}', remedy)
    except RecursionError:
        _fail(error, source, what, 'invalid JSON: nested too deeply', remedy)
    except ValueError as e:       # a number of more digits than Python converts
        _fail(error, source, what, 'invalid JSON: a number too long to read'
              if 'digits' in str(e) else f'invalid JSON: {e}', remedy)
    if expect is not None and not _matches(value, expect):
        _fail(error, source, what, f'it holds {_json_type(value)} where {_expected(expect)} '
                                   f'is expected', remedy)
    return value


# ------------------------------------------------------------------------------------ NumPy

def _numpy_detail(e: BaseException, damaged: str) -> str:
    """What an exception of numpy or zipfile reading a file says about the file, in words of
    the file (``damaged``: what a file damaged in another way is)."""
    text = str(e)
    if isinstance(e, EOFError) or text.startswith('EOF') or 'greater than file size' in text \
            or 'cannot reshape' in text:
        return 'cut short: it holds less data than its header says'
    if isinstance(e, MemoryError):
        return 'its header declares more data than memory holds'
    if 'Object arrays' in text or 'Python objects' in text or 'pickled' in text:
        return 'it holds Python objects (pickled data), which are never loaded'
    crc = re.match(r"Bad CRC-32 for file '(.*)'$", text)
    if crc:
        return f'the data of {crc.group(1)} in it is damaged: its checksum does not match'
    if isinstance(e, zipfile.BadZipFile) or (isinstance(e, OSError) and 'npz' in damaged):
        return 'a damaged or cut short zip archive'
    if 'header' in text.lower() or 'format version' in text:
        return 'its NumPy header is damaged'
    return damaged


def read_npz(path, what: str = 'NumPy archive (.npz)', remedy: str | None = FIX,
             keys: Iterable[str] | None = None,
             error: type[Exception] = FileReadError) -> dict[str, np.ndarray]:
    """``{name: array}`` of the ``.npz`` archive ``path``: every array, or those of ``keys``
    that it holds (``keys`` it does not hold are left out). Nothing is unpickled.

    Raises:
        error: the file is missing, a folder, unreadable, empty, an ``.npy`` array rather than
            an archive, not a zip archive, damaged or cut short (its checksums), or holds
            Python objects.
    """
    path = _name(path)
    head = _read_bytes(path, what, remedy, error, size=8)
    if head.startswith(_NPY_MAGIC):
        _fail(error, path, what, 'a NumPy array file, not an .npz archive', remedy)
    if not head.startswith(_ZIP_MAGIC):
        _fail(error, path, what, 'not an .npz archive: it does not start as a zip archive',
              remedy)
    wanted = None if keys is None else set(keys)
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError('not an .npz archive')
        with z:
            return {k: z[k] for k in z.files if wanted is None or k in wanted}
    # What numpy and zipfile raise on bytes that are not what they should be is open-ended (a
    # zip error, ValueError, EOFError, OverflowError, MemoryError, RuntimeError for an
    # "encrypted" flag, tokenize's TokenError from a damaged header, ...): the file's fault.
    except Exception as e:  # noqa: BLE001
        _fail(error, path, what, _numpy_detail(e, 'a damaged .npz archive'), remedy)


def read_npy(path, what: str = 'NumPy array file (.npy)', remedy: str | None = FIX,
             error: type[Exception] = FileReadError) -> np.ndarray:
    """The array of the ``.npy`` file ``path`` (a copy in memory). The file is mapped first, so
    that a header declaring more data than the file holds is refused rather than allocated.
    Nothing is unpickled.

    Raises:
        error: the file is missing, a folder, unreadable, empty, an ``.npz`` archive, not a
            NumPy array file, cut short, or holds Python objects.
    """
    path = _name(path)
    head = _read_bytes(path, what, remedy, error, size=8)
    if head.startswith(_ZIP_MAGIC):
        _fail(error, path, what, 'an .npz archive of arrays, not one array', remedy)
    if not head.startswith(_NPY_MAGIC):
        _fail(error, path, what, 'it does not start with the NumPy header', remedy)
    try:
        array = np.load(path, allow_pickle=False, mmap_mode='r')
        if not isinstance(array, np.ndarray):
            raise ValueError('not a NumPy array file')
        return np.array(array)
    # What numpy and zipfile raise on bytes that are not what they should be is open-ended (a
    # zip error, ValueError, EOFError, OverflowError, MemoryError, RuntimeError for an
    # "encrypted" flag, tokenize's TokenError from a damaged header, ...): the file's fault.
    except Exception as e:  # noqa: BLE001
        _fail(error, path, what, _numpy_detail(e, 'a damaged NumPy array file'), remedy)


# --------------------------------------------------------------------------- EXR and images

_EXR_MAGIC = b'\x76\x2f\x31\x01'
_IMAGE_MAGIC = {b'\x89PNG\r\n\x1a\n': 'PNG', b'\xff\xd8\xff': 'JPEG'}


def _image_detail(e: BaseException, damaged: str) -> str:
    """What an exception of a decoder (OpenEXR, Pillow, imageio) says about the file."""
    text = ' '.join(str(e).split()).lower()
    if isinstance(e, MemoryError):
        return 'its header declares more pixels than memory holds'
    if 'truncat' in text or 'premature' in text or 'end of file' in text or 'eof' in text \
            or isinstance(e, EOFError):
        return 'cut short: it holds less data than its header says'
    return damaged


def read_exr(path, what: str = 'EXR image', remedy: str | None = FIX,
             error: type[Exception] = FileReadError,
             separate_channels: bool = False) -> tuple[dict, dict[str, np.ndarray]]:
    """``(header, {channel name: pixels})`` of the single-part OpenEXR file ``path``, as
    ``OpenEXR.File(path, separate_channels=...)`` gives them (the pixels of a deep file are
    arrays of each pixel's samples), every pixel read.

    Raises:
        error: the file is missing, a folder, unreadable, empty, not an OpenEXR file, damaged
            or cut short, or of several parts.
    """
    path = _name(path)
    head = _read_bytes(path, what, remedy, error, size=4)
    if head != _EXR_MAGIC:
        _fail(error, path, what, 'not an OpenEXR file: it does not start as one', remedy)
    # OpenEXR prints "Warning: Exception raised reading pixel data ..." to sys.stdout for
    # pixels it cannot read (and gives no part): that text is kept from the output, the
    # error says it in words; what else is printed meanwhile is printed after.
    printed = io.StringIO()
    try:
        with _printed_to(printed), readable_path(path) as readable, \
                OpenEXR.File(readable, separate_channels=separate_channels) as f:
            if not f.parts:
                _fail(error, path, what, 'a damaged or cut short OpenEXR file', remedy)
            if len(f.parts) != 1:
                _fail(error, path, what, f'{len(f.parts)} parts where one is expected', remedy)
            header = dict(f.header())
            channels = {name: channel.pixels for name, channel in f.channels().items()}
    except error:
        raise
    # What OpenEXR raises on bytes that are not what they should be is open-ended
    # (RuntimeError, ValueError, MemoryError, ...): the file's fault.
    except Exception as e:  # noqa: BLE001
        _fail(error, path, what, _image_detail(e, 'a damaged or cut short OpenEXR file'),
              remedy)
    return header, channels


@contextlib.contextmanager
def _printed_to(buffer: io.StringIO):
    """``sys.stdout`` into ``buffer`` for the time of the ``with``; then its lines other than
    OpenEXR's warnings of unreadable pixels printed to the real one."""
    try:
        with contextlib.redirect_stdout(buffer):
            yield
    finally:
        kept = [line for line in buffer.getvalue().splitlines(keepends=True)
                if not line.startswith('Warning: Exception raised reading pixel data')]
        if kept:
            sys.stdout.write(''.join(kept))


@contextlib.contextmanager
def open_photo(path, what: str = 'photo', remedy: str | None = FIX,
               error: type[Exception] = FileReadError, pixels: bool = True):
    """A Pillow image of the file ``path`` (any format Pillow reads), open for the time of the
    ``with``, its EXIF read and (``pixels``, the default) its pixels decoded before it is
    given, so that what the caller does with it meets no damage of the file; ``pixels=False``
    for its size and EXIF alone.

    Raises:
        error: the file is missing, a folder, unreadable, empty, not an image Pillow reads,
            damaged or cut short.
    """
    from PIL import Image     # deferred: only photos for structure from motion need Pillow's
    path = _name(path)
    _read_bytes(path, what, remedy, error, size=8)
    try:
        img = Image.open(path)
    except Exception as e:  # noqa: BLE001 - Pillow's refusals are open-ended, as read_image's
        _fail(error, path, what, _image_detail(e, 'not an image Pillow reads'), remedy)
    with img:
        try:
            img.getexif()
            if pixels:
                img.load()
        except Exception as e:  # noqa: BLE001
            _fail(error, path, what, _image_detail(e, 'a damaged image'), remedy)
        yield img


def read_image(path, what: str = 'image', remedy: str | None = FIX,
               error: type[Exception] = FileReadError) -> np.ndarray:
    """The pixels of the PNG or JPEG file ``path`` as ``imageio.v3.imread`` gives them
    (``uint8`` (H, W[, C]) for an 8-bit image), every pixel read.

    Raises:
        error: the file is missing, a folder, unreadable, empty, neither a PNG nor a JPEG,
            damaged or cut short.
    """
    path = _name(path)
    head = _read_bytes(path, what, remedy, error, size=8)
    if not any(head.startswith(magic) for magic in _IMAGE_MAGIC):
        _fail(error, path, what, 'neither a PNG nor a JPEG image: it does not start as one',
              remedy)
    kind = next(name for magic, name in _IMAGE_MAGIC.items() if head.startswith(magic))
    try:
        return iio.imread(path)
    # What Pillow and imageio raise on bytes that are not what they should be is open-ended
    # (OSError, SyntaxError, ValueError, zlib.error, ...): the file's fault.
    except Exception as e:  # noqa: BLE001
        _fail(error, path, what, _image_detail(e, f'a damaged {kind} image'), remedy)
