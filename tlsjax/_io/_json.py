"""Strict, atomic JSON files and output paths checked before any work is done.

Every JSON file tlsjax writes goes through :func:`write_json_file`: values are converted to
plain JSON types, NaN and infinities become ``null`` (undefined), ``json`` is called with
``allow_nan=False`` as a last guard, and the text is written to a temporary file in the target
folder that then replaces the target (``os.replace`` is atomic on one file system), so a reader
never sees half a file and a failure leaves the previous file, if any, untouched.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import tempfile

import numpy as np


def to_json_value(obj):
    """``obj`` as plain JSON types: dicts (string keys), lists, str, int, float, bool, None.

    NaN and +-inf become None; numpy scalars and arrays, tuples, enums and dataclasses are
    converted. Anything else is refused with a TypeError (it has no JSON meaning).
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, enum.Enum):
        return to_json_value(obj.value)
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, np.ndarray):
        return to_json_value(obj.tolist())
    if isinstance(obj, dict):
        return {str(k): to_json_value(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_value(v) for v in obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_json_value(dataclasses.asdict(obj))
    raise TypeError(f"cannot write a {type(obj).__name__} to JSON")


def dumps_strict(obj, indent: int = 2) -> str:
    """Strict JSON text of :func:`to_json_value` (``allow_nan=False``)."""
    return json.dumps(to_json_value(obj), indent=indent, allow_nan=False) + "\n"


def _nearest_existing(path: str) -> str:
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        up = os.path.dirname(parent)
        if up == parent:
            break
        parent = up
    return parent


def _check_folder_writable(folder: str, path: str, option: str) -> None:
    """The folder that will hold ``path`` (or its nearest existing ancestor) must be a writable
    directory; a file on the way is named."""
    ancestor = _nearest_existing(folder) if not os.path.exists(folder) else folder
    if not os.path.isdir(ancestor):
        raise ValueError(
            f"{option}{path}: cannot be written: {ancestor} is a file, not a directory"
        )
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"{option}{path}: cannot be written: no permission to write in {ancestor}")
    # Permissions do not tell everything (a read-only mount, a pseudo file system, root):
    # creating and removing a file there does.
    try:
        with tempfile.TemporaryFile(dir=ancestor):
            pass
    except OSError as err:
        raise ValueError(
            f"{option}{path}: cannot be written: no file can be created in {ancestor} "
            f"({err.strerror or err})"
        ) from None


def check_output_file(path, option: str = "") -> None:
    """Refuse, before any work, an output file path that cannot be written: a directory, a path
    through a file, a folder without write permission, a read-only file. ``option`` (e.g.
    ``"--json "``) prefixes the one-line ValueError."""
    if path is None:
        return
    path = os.fspath(path)
    if not path or path.endswith(os.sep):
        raise ValueError(f"{option}{path!r}: not a file name")
    if os.path.isdir(path):
        raise ValueError(f"{option}{path}: is a directory; give a file name")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise ValueError(f"{option}{path}: cannot be written: the file is read-only")
    folder = os.path.dirname(os.path.abspath(path))
    _check_folder_writable(folder, path, option)


def check_output_dir(path, option: str = "") -> None:
    """Refuse, before any work, an output folder that is a file, lies under a file or cannot
    be written to."""
    if path is None:
        return
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"{option}{path}: is a file, not a directory")
    _check_folder_writable(os.path.abspath(path), path, option)


def make_parent(path, option: str = "") -> None:
    """Create the folder of ``path``; a failure is one ValueError naming the path."""
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"{option}{os.fspath(path)}: cannot create its folder ({err.strerror})"
        ) from None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text_atomic(path, text: str, option: str = "") -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and
    ``os.replace``: the file is complete or untouched. OSError -> one-line ValueError."""
    path = os.fspath(path)
    check_output_file(path, option)
    make_parent(path, option)
    folder = os.path.dirname(os.path.abspath(path))
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tlsjax-", suffix=".tmp", dir=folder)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; a result file is not
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise ValueError(f"{option}{path}: cannot be written ({err.strerror or err})") from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def write_json_file(path, obj, option: str = "") -> dict:
    """Write ``obj`` as strict JSON (NaN/inf -> null), atomically; returns what was written."""
    value = to_json_value(obj)
    text = json.dumps(value, indent=2, allow_nan=False) + "\n"
    write_text_atomic(path, text, option)
    return value


def read_result_json(source) -> dict:
    """A tlsjax result JSON as a dict; a one-line ValueError naming the file otherwise."""
    try:
        with open(source, encoding="utf-8") as fh:
            doc = json.load(fh)
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{source}: not a readable result JSON ({err})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("aps"), dict):
        raise ValueError(f"{source}: not a tlsjax result JSON (no 'aps' object)")
    return doc
