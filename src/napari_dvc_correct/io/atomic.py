"""Atomic writes: one file (temporary file + rename) or a whole set of files (temporary folder + swap).

Every temporary name holds :data:`TEMP_MARK`, the id of the writing process and a tag of its
machine (``.NAME.ndc-tmp-PID-HOST-RANDOM.SUFFIX``), so a leftover is recognisable: a process
killed with SIGKILL cannot remove its temporary file, and the next write into the same folder
removes the leftovers of processes of this machine that no longer run (:func:`remove_stale`);
files of other machines (a shared file system) are never touched. Outputs get the mode a plain
``open(path, "w")`` would give them (``0o666 & ~umask``); overwriting keeps the existing file's mode.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
import shutil
import signal
import socket
import stat
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

try:  # POSIX: an advisory lock other processes see too
    import fcntl
except ImportError:  # Windows: the lock below holds threads of this process only
    fcntl = None

#: Part of every temporary name this package makes (files and folders).
TEMP_MARK = ".ndc-tmp-"
#: File that marks a folder as an output set written by :func:`atomic_dir`.
SET_MARKER = ".napari-dvc-correct-set.json"

_STALE = re.compile(r"^\..*" + re.escape(TEMP_MARK) + r"(\d+)-([0-9a-f]{6})-[0-9a-f]+")
#: Tag of this machine in temporary names.
HOST_TAG = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]
_umask_lock = threading.Lock()


#: Targets renamed into place since :func:`reset_committed` (the command line says so when a
#: signal lands after them: the new outputs are complete).
_committed: list[Path] = []


def committed() -> list[Path]:
    """The outputs this process completed (renamed into place) since :func:`reset_committed`."""
    return list(_committed)


def reset_committed() -> None:
    _committed.clear()


def _commit(paths) -> None:
    """Record outputs now complete (not the files of a set still in its temporary folder)."""
    _committed.extend(p for p in map(Path, paths) if TEMP_MARK not in str(p.parent))


def _umask() -> int:
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def output_mode(path: str | os.PathLike) -> int:
    """The permission bits a new output at ``path`` gets: the existing file's, else 0o666 & ~umask."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        return 0o666 & ~_umask()


def temp_name(path: Path, pid: int | None = None) -> Path:
    """A recognisable temporary name next to ``path`` (of process ``pid``), keeping its suffixes."""
    path = Path(path)
    suffix = "".join(path.suffixes)
    pid = os.getpid() if pid is None else int(pid)
    token = secrets.token_hex(4)
    return path.with_name(f".{path.name}{TEMP_MARK}{pid}-{HOST_TAG}-{token}{suffix}")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and folders in ``folder`` left by processes no longer running.

    Only names made by :func:`temp_name` on this machine are touched, and only when their process
    id is not a running process (so a concurrent run's temporary files stay).
    """
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = _STALE.match(entry.name)
        if match is None or match.group(2) != HOST_TAG or _alive(int(match.group(1))):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def scratch_dir(prefix: str, parent: str | os.PathLike | None = None) -> Path:
    """A new private folder for a run's temporary arrays, named like every temporary of ours.

    The name is :func:`temp_name` of ``parent / prefix`` (``.PREFIX.ndc-tmp-PID-HOST-RANDOM``),
    so a run killed with SIGKILL leaves a folder the next run in ``parent`` recognises as dead
    and removes (:func:`remove_stale`, called here first). ``parent`` defaults to the system's
    temporary folder (``TMPDIR``). The caller removes the folder when done.
    """
    import tempfile

    parent = Path(tempfile.gettempdir() if parent is None else parent)
    remove_stale(parent)
    path = temp_name(parent / prefix)
    path.mkdir(mode=0o700)
    return path


def check_writable(folder: str | os.PathLike) -> None:
    """Raise ``PermissionError`` ("cannot write into FOLDER (why)") if no file can be made in
    ``folder``: the probe does what a write does first, create a temporary file there."""
    folder = Path(folder)
    probe = temp_name(folder / "probe")
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as error:
        raise PermissionError(f"cannot write into {folder} ({error.strerror or error})") from None
    os.unlink(probe)


def _folder(path: Path) -> Path:
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.exists():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    return folder


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    If the body raises (or the process is interrupted), the temporary file is removed and
    ``path`` is left untouched, so a failed or cancelled write never destroys an earlier result.

    The temporary name keeps the suffix of ``path`` so libraries that pick a format from the
    extension (numpy's ``.npz``, tifffile, h5py) behave as for the final name. The final file
    gets :func:`output_mode`.
    """
    path = Path(path)
    folder = _folder(path)
    remove_stale(folder)
    mode = output_mode(path)
    temp = temp_name(path)
    try:
        fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        yield temp
        os.chmod(temp, mode)
        os.replace(temp, path)
        _commit([path])
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            temp.unlink()
        raise


@contextlib.contextmanager
def atomic_files(*paths: str | os.PathLike) -> Iterator[list[Path]]:
    """:func:`atomic_path` for several files that belong together (a field and its side file).

    Yields one temporary path per target; on success all are renamed into place with SIGINT and
    SIGTERM held back, so either every target is new or none is: a target that is a folder is
    refused before the body runs, and if a rename fails the targets already renamed get their
    earlier content back (kept as a hard link, or a copy, until all renames are done).

    Raises
    ------
    ValueError
        If a target is an existing folder (nothing is written then).
    """
    targets = [Path(p) for p in paths]
    for target in targets:
        if target.is_dir():
            raise ValueError(f"{target} is a folder: give a file name")
    for folder in {_folder(p) for p in targets}:
        remove_stale(folder)
    modes = [output_mode(p) for p in targets]
    temps = [temp_name(p) for p in targets]
    try:
        yield temps
        for temp, mode in zip(temps, modes):
            os.chmod(temp, mode)
        with _signals_blocked():
            _replace_all(temps, targets)
            _commit(targets)
    except BaseException:
        for temp in temps:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        raise


def _keep_copy(target: Path) -> Path | None:
    """A hard link (or a copy) of an existing ``target`` under a temporary name; None if absent."""
    if not target.is_file():
        return None
    backup = temp_name(target)
    try:
        os.link(target, backup)
    except OSError:
        shutil.copy2(target, backup)
    return backup


def _replace_all(temps: list[Path], targets: list[Path]) -> None:
    """Rename every temporary file onto its target; on a failure undo the renames already made."""
    done: list[tuple[Path, Path | None]] = []
    try:
        for temp, target in zip(temps, targets):
            done.append((target, _keep_copy(target)))
            os.replace(temp, target)
    except BaseException:
        for target, backup in reversed(done):
            with contextlib.suppress(OSError):
                if backup is not None:
                    os.replace(backup, target)
                elif target.is_file():
                    target.unlink()
        raise
    finally:
        for _, backup in done:
            if backup is not None:
                with contextlib.suppress(FileNotFoundError):
                    backup.unlink()


def is_output_set(folder: str | os.PathLike, patterns: Iterable[str] = ()) -> bool:
    """True if ``folder`` may be replaced as a whole by a new output set.

    That is: it is empty, it holds :data:`SET_MARKER` (written by :func:`atomic_dir`) and nothing
    that its manifest does not list, or every entry in it is a file matching one of ``patterns``
    (globs of the command's own outputs, for sets written before the marker existed).
    """
    return not foreign_entries(folder, patterns)


def foreign_entries(folder: str | os.PathLike, patterns: Iterable[str] = ()) -> list[str]:
    """The names in ``folder`` that a new output set may not delete (empty: it may replace it).

    With :data:`SET_MARKER`: every entry its manifest's ``files`` does not list (a user's file
    added to an output folder after the run). Without it: every entry unless all are files
    matching ``patterns``.
    """
    folder = Path(folder)
    entries = sorted(folder.iterdir())
    names = [entry.name for entry in entries]
    marker = folder / SET_MARKER
    if marker.is_file():
        try:
            listed = json.loads(marker.read_text(encoding="utf-8")).get("files", [])
            listed = {str(name) for name in listed}
        except (OSError, ValueError, AttributeError):
            return [name for name in names if name != SET_MARKER]  # unreadable: trust nothing
        return [name for name in names if name != SET_MARKER and name not in listed]
    patterns = tuple(patterns)
    if patterns and all(entry.is_file() and any(entry.match(p) for p in patterns)
                        for entry in entries):  # fmt: skip
        return []
    return names


@contextlib.contextmanager
def _signals_blocked() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back until the block is done, then act on the first one.

    Python runs signal handlers in the main thread, whichever thread the operating system
    delivered the signal to (numba and dask keep threads of their own, which a
    ``pthread_sigmask`` of the main thread does not cover): the handlers are swapped for one
    that only records the signal, and the recorded signal is passed to the previous handler
    once the block is over.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(
        signal, "pthread_sigmask"
    ):  # not the main thread, or Windows (no signal masks): written as is
        yield
        return
    pending: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {number: signal.signal(number, lambda n, frame: pending.append(n))
                for number in held}  # fmt: skip
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, set(held))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for number, handler in previous.items():
            signal.signal(number, handler)
    if pending:
        handler = previous[pending[0]]
        if callable(handler):
            handler(pending[0], None)
        elif handler == signal.SIG_DFL:
            os.kill(os.getpid(), pending[0])


@contextlib.contextmanager
def locked_folder(folder: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive advisory lock (``flock``) on ``folder`` for the block: writers that
    read a file of the folder, decide and write (a side file shared by several outputs) take
    turns, in this process (other threads) and in others."""
    with _locked(Path(folder)):
        yield


_folder_locks: dict[str, threading.Lock] = {}
_folder_locks_guard = threading.Lock()


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """The threads of this process take turns on a lock of their own per folder (``flock``
    alone does not order two threads that each open the folder); on POSIX the folder's
    ``flock`` then makes other processes wait too."""
    with _folder_locks_guard:
        lock = _folder_locks.setdefault(os.path.realpath(folder), threading.Lock())
    with lock:
        if fcntl is None:
            yield
            return
        fd = os.open(folder, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_dir(
    path: str | os.PathLike, patterns: Iterable[str] = (), manifest: dict | None = None
) -> Iterator[Path]:
    """Yield an empty temporary folder next to ``path``; on success it replaces ``path`` whole.

    The body writes every file of the set into the yielded folder. On success the folder gets
    :data:`SET_MARKER` (a JSON manifest: the files and ``manifest``) and is swapped with
    ``path``: the earlier set (if any) is removed as a whole, so no stale file of an earlier run
    survives. If the body raises or the process is interrupted, the temporary folder is removed
    and ``path`` is as it was. Two runs into one ``path`` never mix: each builds its own folder
    and the swaps are serialised (the last to finish wins).

    Raises
    ------
    ValueError
        If ``path`` exists and is a file, or a folder that is not an output set
        (:func:`is_output_set` with ``patterns``) — it is never replaced then.
    """
    path = Path(path)
    folder = _folder(path)
    patterns = tuple(patterns)
    check_set_target(path, patterns)
    remove_stale(folder)
    temp = temp_name(path)
    temp.mkdir(mode=0o777)
    try:
        yield temp
        files = sorted(p.name for p in temp.iterdir())
        with open(temp / SET_MARKER, "w") as stream:
            json.dump({"files": files, **(manifest or {})}, stream, indent=1, default=str)
        old = temp_name(path)
        with _signals_blocked(), _locked(folder):
            check_set_target(path, patterns)
            try:
                os.rename(path, old)
            except FileNotFoundError:
                old = None
            os.rename(temp, path)
            _commit([path])
            if old is not None:  # still held back: the earlier set never stays behind
                shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(temp, ignore_errors=True)
        raise


def check_set_target(path: str | os.PathLike, patterns: Iterable[str] = ()) -> None:
    """Raise ``ValueError`` if ``path`` exists and may not be replaced by an output set."""
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise ValueError(f"{path} exists and is not a folder")
    foreign = foreign_entries(path, tuple(patterns)) if path.is_dir() else []
    if foreign:
        shown = ", ".join(foreign[:3]) + (
            f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        )
        raise ValueError(
            f"{path} is a folder with files this tool did not write ({shown}): choose a new or "
            "empty folder (its whole content is replaced)"
        )
