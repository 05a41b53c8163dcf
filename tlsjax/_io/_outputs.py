"""Output paths: checked before any work, never an input, written atomically.

Every command names its inputs and its outputs to :func:`check_outputs` before it reads a
file: an output that cannot be written, that is one of the inputs (compared as resolved paths,
through symbolic links, and by device and inode for hard links), or that two outputs share, is
refused in one line naming the option and the path. Missing parent folders of an output are
created (by every command alike), so only a path under a file or in a folder without write
permission is refused.

Every file is written through :func:`atomic_output`: the writer writes a temporary file in the
target folder, with the target's name ending (writers choose the format by it), which replaces
the target only when the writer has finished (``os.replace`` is atomic on one file system). An
error or Ctrl-C leaves no half-written file and the previous file, if any, untouched.
"""

from __future__ import annotations

import contextlib
import os
import tempfile


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
    if not path or path.endswith(os.sep) or os.path.basename(path) in (".", ".."):
        raise ValueError(f"{option}{path!r}: not a file name")
    if os.path.isdir(path):
        raise ValueError(f"{option}{path}: is a directory; give a file name")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise ValueError(f"{option}{path}: cannot be written: the file is read-only")
    _check_folder_writable(os.path.dirname(os.path.abspath(path)), path, option)


def check_output_dir(path, option: str = "") -> None:
    """Refuse, before any work, an output folder that is a file, lies under a file or cannot
    be written to."""
    if path is None:
        return
    path = os.fspath(path)
    if not path:
        raise ValueError(f"{option}{path!r}: not a folder name")
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"{option}{path}: is a file, not a directory")
    _check_folder_writable(os.path.abspath(path), path, option)


def same_file(a, b) -> bool:
    """True when paths ``a`` and ``b`` name one file: equal after resolving symbolic links
    (the file need not exist yet), or the same device and inode (hard links, case-insensitive
    file systems)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def _expand(outputs):
    """(option, path) for every file the outputs name: a file output as itself, a folder
    output ``(option, folder, names)`` as each ``folder/name``."""
    for entry in outputs:
        option, path = entry[0], entry[1]
        if path is None:
            continue
        if len(entry) > 2:
            for name in entry[2]:
                yield option, os.path.join(os.fspath(path), name)
        else:
            yield option, os.fspath(path)


def _label(option: str) -> str:
    return option.strip() + " " if option.strip() else ""


def check_outputs(outputs, inputs=()) -> None:
    """Refuse, before any work, outputs that cannot be written, that would write over an input
    or that two outputs share; one ValueError naming the option and the path.

    ``outputs``: ``(option, path)`` for a file (``path`` None: not asked for) or
    ``(option, folder, names)`` for files written into a folder; ``inputs``: ``(label, path)``
    of every file the command reads (None entries skipped). Missing parent folders are fine:
    the writers create them.
    """
    for entry in outputs:
        if entry[1] is None:
            continue
        if len(entry) > 2:
            check_output_dir(entry[1], _label(entry[0]))
        else:
            check_output_file(entry[1], _label(entry[0]))
    files = list(_expand(outputs))
    inputs = [(label, os.fspath(p)) for label, p in inputs if p is not None]
    for option, path in files:
        for label, src in inputs:
            if same_file(path, src):
                raise ValueError(
                    f"{_label(option)}{path}: is the input {label} {src}; tlsjax never writes over "
                    "its inputs: give the output another path"
                )
    for i, (opt_a, a) in enumerate(files):
        for opt_b, b in files[i + 1 :]:
            if same_file(a, b):
                both = f"{_label(opt_a)}{a} and {_label(opt_b)}{b}"
                raise ValueError(f"{both} are the same file; give each output its own path")


def make_parent(path, option: str = "") -> None:
    """Create the folder of ``path``; a failure is one ValueError naming the path."""
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"{_label(option)}{os.fspath(path)}: cannot create its folder ({err.strerror})"
        ) from None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _name_ending(path: str) -> str:
    """The extension a writer chooses the format by (``.csv``, ``.laz``; empty without one)."""
    return os.path.splitext(os.path.basename(path))[1]


@contextlib.contextmanager
def atomic_output(path, option: str = "", *, companions=()):
    """Yield a temporary path in ``path``'s folder, ending like ``path``; when the block ends
    without an exception it replaces ``path`` (and ``tmp + suffix`` replaces ``path + suffix``
    for each of ``companions``, side files such as ``.sigma_mm.txt``). On any exception,
    Ctrl-C included, the temporary files are removed and ``path`` is left as it was. The
    folder is created if missing; a failure to create or rename is one ValueError naming
    ``path`` (errors of the writer itself pass through unchanged)."""
    path = os.fspath(path)
    make_parent(path, option)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tlsjax-", suffix=_name_ending(path), dir=folder)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; a result file is not
    except OSError as err:
        raise ValueError(f"{_label(option)}{path}: cannot be written ({err.strerror})") from None
    made = [tmp] + [tmp + s for s in companions]
    try:
        yield tmp
        try:
            for s in companions:
                if os.path.exists(tmp + s):
                    os.replace(tmp + s, path + s)
            os.replace(tmp, path)
        except OSError as err:
            raise ValueError(
                f"{_label(option)}{path}: cannot be written ({err.strerror or err})"
            ) from None
    finally:
        for leftover in made:
            if os.path.lexists(leftover):
                os.unlink(leftover)


def write_text_atomic(path, text: str, option: str = "") -> None:
    """Write ``text`` to ``path`` through :func:`atomic_output`: the file is complete or
    untouched. OSError -> one-line ValueError."""
    path = os.fspath(path)
    check_output_file(path, _label(option))
    with atomic_output(path, option) as tmp:
        try:
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(text)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as err:
            raise ValueError(
                f"{_label(option)}{path}: cannot be written ({err.strerror or err})"
            ) from None
