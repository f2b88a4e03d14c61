"""Files written whole or not at all: the one atomic write, and the temporaries it leaves behind a kill.

Every file the project writes goes through :func:`atomic_write` (a temporary
file created exclusively beside the target, flushed, fsynced, then renamed
over it), so a crash or a kill never leaves a half-written file at a final
path; a temporary's name says which process made it, so the next run removes
those of dead processes (:func:`remove_dead_temporaries`).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

__all__ = [
    "atomic_write",
    "atomic_write_all",
    "remove_dead_temporaries",
    "tmp_prefix",
    "TMP_MARK",
    "is_temporary_name",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_savez",
]

TMP_MARK = ".~genre"  # in every temporary name the project makes: ``.BASE.~genrePID-RANDOM`` (no user's own file looks so)
_PID_DIGITS = 7  # the longest Linux pid (pid_max ≤ 2**22 = 4194304)
_RANDOM_CHARS = 8  # mkstemp's random part


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder if str(folder) else ".", "PC_NAME_MAX"))
    except (OSError, ValueError, TypeError):
        return 255


def _tmp_base(path: Path) -> str:
    """``path``'s name, cut (whole characters) so that its longest temporary name fits the file system's name limit."""
    room = _name_max(path.parent) - (1 + len(TMP_MARK) + _PID_DIGITS + 1 + _RANDOM_CHARS)
    name = path.name
    while name and len(os.fsencode(name)) > room:
        name = name[:-1]
    return name


def tmp_prefix(path: Path) -> str:
    """The hidden prefix of ``path``'s temporary files: ``.NAME.~genrePID-`` (8 random characters follow).

    NAME is cut when needed so that the temporary name fits within the file
    system's name limit (255 bytes) for any legal name of ``path``.
    """
    return f".{_tmp_base(Path(path))}{TMP_MARK}{os.getpid()}-"


def is_temporary_name(name: str) -> bool:
    """Whether ``name`` is one the project gives its temporary files (``.BASE.~genrePID-XXXXXXXX``)."""
    head, mark, tail = name.rpartition(TMP_MARK)
    if not mark or not head.startswith("."):
        return False
    pid, dash, rand = tail.partition("-")
    return pid.isdigit() and bool(dash) and len(rand) == _RANDOM_CHARS and rand.isascii() and (rand.replace("_", "").isalnum())


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (another user's counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # (EPERM: alive, another user's)
        return True
    return True


def remove_dead_temporaries(path: str | os.PathLike) -> int:
    """Delete ``path``'s temporary files left by processes that no longer run (killed mid-write); returns how many.

    Only names the project makes are touched (:func:`is_temporary_name`:
    ``.NAME.~genrePID-XXXXXXXX``, owned by this user): a user's own
    ``.NAME.tmp-PID-x`` file is never deleted.
    """
    path = Path(path)
    head = f".{_tmp_base(path)}{TMP_MARK}"
    removed = 0
    try:
        entries = list(os.scandir(path.parent if str(path.parent) else "."))
    except OSError:
        return 0
    for entry in entries:
        if not entry.name.startswith(head) or not is_temporary_name(entry.name):
            continue
        pid_text = entry.name[len(head):].split("-", 1)[0]
        try:
            mine = entry.stat(follow_symlinks=False).st_uid == os.geteuid() and entry.is_file(follow_symlinks=False)
        except OSError:
            continue
        if mine and pid_text.isdigit() and int(pid_text) != os.getpid() and not pid_alive(int(pid_text)):
            try:
                os.unlink(entry.path)
                removed += 1
            except OSError:
                pass
    return removed


def _write_temporary(path: Path, writer: Callable[[BinaryIO], Any]) -> Path:
    """``writer(binary_file)`` on a new temporary file beside ``path`` (flushed, fsynced, the usual permissions).

    Created with ``O_CREAT | O_EXCL`` by ``mkstemp`` (never follows a planted
    link), named ``tmp_prefix(path)`` + 8 random characters; removed again if
    anything fails (a signal's exception included).  Returns its path.
    """
    remove_dead_temporaries(path)
    fd, tmp_name = tempfile.mkstemp(prefix=tmp_prefix(path), dir=path.parent if str(path.parent) else ".")
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def atomic_write_all(items) -> list[Path]:
    """Write several files as one unit: every ``(path, writer)`` to its temporary first, then rename them all, in order.

    If any writer fails (or a signal interrupts), every temporary is removed
    and no target is touched; the renames come only once all are written
    (microseconds apart: a textured OBJ's texture, .mtl and .obj appear
    together).  Returns the paths.
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for path, writer in items:
            path = Path(path)
            staged.append((_write_temporary(path, writer), path))
        for tmp, path in staged:
            os.replace(tmp, path)
    finally:
        for tmp, _ in staged:
            if os.path.lexists(tmp):
                os.unlink(tmp)
    return [path for _, path in staged]


def atomic_write(path: str | os.PathLike, writer: Callable[[BinaryIO], Any]) -> Path:
    """Call ``writer(binary_file)`` on a new temporary file beside ``path``, then rename it to ``path``.

    The temporary file is created with ``O_CREAT | O_EXCL`` (never follows a
    planted link) in the target's folder (so the rename is atomic), and is
    removed if ``writer`` or the rename fails; the error propagates.
    Temporary files of ``path`` left by dead processes are removed first.
    Returns ``path`` as a :class:`~pathlib.Path`.
    """
    return atomic_write_all([(path, writer)])[0]


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once at import: os.umask can only be read by setting it


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda fh: fh.write(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, data: Any, indent: int | None = 1, ensure_ascii: bool = True) -> Path:
    """Write ``data`` as JSON (with a final newline) to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(data, indent=indent, ensure_ascii=ensure_ascii) + "\n")


def atomic_savez(path: str | os.PathLike, **arrays) -> Path:
    """Write NumPy arrays as a compressed ``.npz`` to ``path`` atomically."""
    import numpy as np

    return atomic_write(path, lambda fh: np.savez_compressed(fh, **arrays))
