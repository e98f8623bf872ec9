"""Atomic file output: nothing the calibration engine writes is ever left half-way (`fitting.files`).

Public for scripts that write their own results the same way (`experiments`): `atomic_file`,
`atomic_write_bytes`, `atomic_write_text`, `atomic_directory`, `check_writable`, `save_json`, `to_jsonable`.

Every writer goes through a temporary sibling (same directory, so the final `os.replace` is an atomic rename on the
same filesystem), is flushed and fsync'ed, and only then renamed onto the destination. On any exception —
`KeyboardInterrupt` included — the temporary is removed and the destination is untouched.
"""

import contextlib
import ctypes
import errno
import json
import math
import os
import re
import shutil
import stat
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from piezojax import PiezojaxValueError

_TMP_TAG = ".tmp-"
MARKER = ".piezojax"
"""Name of the marker file `atomic_directory(..., kind=...)` writes into a folder, so that a later `overwrite` can
recognise a previous output of the same kind (and refuses to replace anything else)."""

# `.NAME.tmp-PID-sSTART-...`: the writer's process id and start time (the start time absent from temporaries of
# earlier versions, and where the system does not give it)
_TEMP_PID = re.compile(re.escape(_TMP_TAG) + r"(\d+)-(?:s(\d+)-)?")
_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # the disk (or the user's quota) is full, or the file too large


def _describe_os_error(e: OSError) -> str:
    return e.strerror or str(e)


def _temp_prefix(name: str) -> str:
    # The owner's process id and start time are part of every temporary name: the next run can tell a leftover of a
    # killed run (owner gone, or its process id now another process's: removed) from the output of a run still in
    # progress (owner alive: refused).
    start = _start_time(os.getpid())
    return f".{name}{_TMP_TAG}{os.getpid()}-" + ("" if start is None else f"s{start}-")


def _start_time(pid: int) -> str | None:
    """When process `pid` started (clock ticks since boot, Linux's /proc), or None where that is unknown."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return fields[19].decode()  # field 22 of proc(5); the first two (pid, comm) are before the ")"
    except (OSError, IndexError, UnicodeDecodeError):
        return None


def _writer_alive(pid: int, start: str | None) -> bool:
    """Whether the run that named a temporary with `pid` (and `start`, its start time, when recorded) still runs: a
    live process with that id that started at another time is another process (the id was reused)."""
    if pid == os.getpid():
        return start is None or start == _start_time(pid)
    if not _process_alive(pid):
        return False
    return start is None or _start_time(pid) in (None, start)


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. EPERM: it exists, owned by someone else
        return True
    return True


def _temporaries(p: Path) -> list[tuple[Path, int, str | None]]:
    """The temporary siblings of `p` written by `atomic_directory`/`atomic_file`, with their owners' process ids and
    start times (None: not recorded)."""
    try:
        entries = list(os.scandir(p.parent))
    except OSError:
        return []
    prefix = f".{p.name}{_TMP_TAG}"
    out = []
    for entry in entries:
        if not entry.name.startswith(prefix):
            continue
        m = _TEMP_PID.search(entry.name)
        if m:
            out.append((Path(entry.path), int(m.group(1)), m.group(2)))
    return out


def _claim(p: Path) -> None:
    """Remove the temporaries of killed runs next to `p`; refuse if another live process is writing `p` now."""
    for tmp, pid, start in _temporaries(p):
        if pid == os.getpid() and (start is None or start == _start_time(pid)):
            continue
        if _writer_alive(pid, start):
            raise PiezojaxValueError(
                f"another process (pid {pid}) is writing {str(p)!r} right now (its temporary {tmp.name!r} exists); "
                "wait for it to finish or choose another output. If no piezojax run is writing there (a leftover "
                "from before a reboot or from another container, whose process id a live process now has), remove "
                f"{str(tmp)!r}"
            )
        if tmp.is_dir() and not tmp.is_symlink():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                tmp.unlink()


def _protected(p: Path) -> str | None:
    """Why the directory `p` must never be replaced (the working directory, one of its ancestors, the home
    directory), or None."""
    try:
        rp, cwd = p.resolve(), Path.cwd().resolve()
    except (OSError, RuntimeError):  # e.g. a symlink loop in a parent: not the working directory, and not writable
        return None
    if rp == cwd:
        return "it is the working directory"
    if rp in cwd.parents:
        return "it contains the working directory"
    with contextlib.suppress(RuntimeError, OSError):
        if rp == Path.home().resolve():
            return "it is the home directory"
    return None


def _read_marker_data(path: str | os.PathLike) -> dict:
    f = Path(os.fspath(path)) / MARKER
    try:
        data = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def read_marker(path: str | os.PathLike) -> str | None:
    """The kind of output recorded in the marker of the folder `path` (`"fit"`, `"predict"`, ...), or None if it has
    no readable marker (not written by piezojax, or by a version before markers)."""
    kind = _read_marker_data(path).get("kind")
    return kind if isinstance(kind, str) else None


def _folder_entries(p: Path) -> list[str]:
    """Every file and folder below `p` (not following links), as sorted POSIX paths relative to `p`; folders end
    with '/'. The marker itself is left out."""
    out = []
    for root, dirs, files in os.walk(p):
        rel = Path(root).relative_to(p)
        out += [(rel / d).as_posix() + "/" for d in dirs]
        out += [(rel / f).as_posix() for f in files]
    return sorted(e for e in out if e != MARKER)


# what file browsers leave in a folder they show: not a user's data
_OS_METADATA = (".DS_Store", "Thumbs.db", "desktop.ini")


def _foreign_entries(p: Path) -> list[str] | None:
    """What the folder `p` holds that its marker does not list as written with it (files a user added after the
    run; file browsers' metadata aside), or None for a marker without a list (written by a version before the
    lists). A list that is not a list of paths raises `PiezojaxValueError`."""
    data = _read_marker_data(p)
    if "files" not in data:
        return None
    written = data["files"]
    if not (isinstance(written, list) and all(isinstance(e, str) for e in written)):
        raise PiezojaxValueError(f"the marker file {str(p / MARKER)!r} is damaged (its list of the files written is "
                                 "not a list of paths), so what else the folder holds cannot be told")
    written = set(written)

    def metadata(e):
        name = e.rstrip("/").rsplit("/", 1)[-1]
        return name in _OS_METADATA or name.startswith("._")

    return [e for e in _folder_entries(p) if e not in written and not metadata(e)]


class OutputWarning(UserWarning):
    """Something about an output folder the user should know, though the run succeeded (`atomic_directory`)."""


def _set_aside(old: Path, p: Path, kind: str | None) -> Path | None:
    """After `p` was replaced, its previous version sits at the temporary `old`: if that holds what its marker does
    not list (a user added it while the run was computing), move it to a visible sibling of `p` (or, if none can
    be made, leave it at `old`) and return where it is, instead of deleting it; else None."""
    if kind is None:
        return None
    try:
        foreign = _foreign_entries(old)
    except PiezojaxValueError:
        foreign = [MARKER]
    if not foreign:
        return None
    for i in range(1, 1000):
        keep = p.with_name(f"{p.name}.previous" + ("" if i == 1 else f"-{i}"))
        if not os.path.lexists(keep):
            try:
                os.rename(old, keep)
            except OSError:
                continue
            return keep
    return old


def _check_name_length(p: Path) -> None:
    try:
        limit = os.pathconf(p.parent, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    # the temporary sibling adds a dot, the tag, the process id, 8 random characters and (files) the suffix again
    room = limit - len(os.fsencode(_temp_prefix(""))) - 12 - len(os.fsencode(p.suffix))
    n = len(os.fsencode(p.name))
    if n > room:
        raise PiezojaxValueError(
            f"cannot write {str(p)!r}: its name is {n} bytes long; this file system allows names of {limit} bytes, "
            f"and the temporary file beside it needs {limit - room} more, so use at most {room}"
        )


def check_writable(path: str | os.PathLike) -> Path:
    """Check that `path` can be created or replaced, before any long computation starts.

    Tests the parent directory the way the writers use it: by creating and removing a temporary file there
    (`os.access` is not enough on read-only mounts or when running as root).

    **Arguments:**

    - `path`: the file or directory that will be written.

    **Returns:**

    The absolute `Path`. Raises `PiezojaxValueError` naming `path` if it is a symbolic link (replacing it would
    replace the link), if its parent does not exist, is not a directory, or is not writable, or if its name is too
    long for the file system with the temporary's additions.

    ```python
    out = check_writable("results/fit.json")  # fails now, not after an hour of fitting
    ```
    """
    if not os.fspath(path):
        raise PiezojaxValueError("the output path is empty")
    p = Path(os.fspath(path)).expanduser().absolute()
    if p.is_symlink():
        # replacing it would replace the link, not what it points to (and a dangling or looping link cannot be
        # written through): name the real path
        raise PiezojaxValueError(
            f"cannot write {str(p)!r}: it is a symbolic link (to {os.readlink(p)!r}); give the path it stands for, "
            "or remove the link"
        )
    parent = p.parent
    if not parent.exists():
        raise PiezojaxValueError(f"cannot write {str(p)!r}: directory {str(parent)!r} does not exist")
    if not parent.is_dir():
        raise PiezojaxValueError(f"cannot write {str(p)!r}: {str(parent)!r} is not a directory")
    _check_name_length(p)
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=f".{p.name[:64]}{_TMP_TAG}probe-")
    except OSError as e:
        raise PiezojaxValueError(
            f"cannot write {str(p)!r}: directory {str(parent)!r} is not writable ({_describe_os_error(e)})"
        ) from e
    os.close(fd)
    os.unlink(probe)
    return p


def _fsync_directory(directory: Path) -> None:
    # Makes the rename itself durable; not supported everywhere (e.g. Windows), hence best effort.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    # Reading it from /proc avoids briefly changing the process umask (not thread-safe); elsewhere, set and restore.
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    umask = os.umask(0)
    os.umask(umask)
    return umask


def _default_file_mode(existing: Path) -> int:
    # mkstemp creates 0600 files; give the result the mode a plain open() would (or keep the replaced file's mode).
    try:
        return stat.S_IMODE(existing.stat().st_mode)
    except OSError:
        return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Context manager yielding a temporary file path next to `path`; renamed onto `path` on normal exit.

    For writers that want a file name (h5py). The temporary keeps the suffix of `path`, so suffix-sniffing writers
    behave. On any exception the temporary is removed and `path` is untouched.

    **Arguments:**

    - `path`: destination file.

    **Returns:**

    A context manager yielding the temporary `Path` to write to.

    ```python
    with atomic_file("run.h5") as tmp:
        with h5py.File(tmp, "w") as f:
            f["t"] = t
    ```
    """
    p = check_writable(path)
    if p.is_dir():
        raise PiezojaxValueError(f"cannot write file {str(p)!r}: a directory of that name exists")
    _claim(p)
    # the full name in the prefix (run.csv and run.h5 have distinct temporaries), the suffix kept for sniffing writers
    fd, tmp_name = tempfile.mkstemp(dir=p.parent, prefix=_temp_prefix(p.name), suffix=p.suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _default_file_mode(p))
        os.replace(tmp, p)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        _raise_full(e, p)
        raise
    _fsync_directory(p.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically: temp file in the same directory, fsync, `os.replace`.

    **Arguments:**

    - `path`: destination file (its parent directory must exist).
    - `data`: the bytes to write.

    **Returns:**

    The absolute `Path` written. Raises `PiezojaxValueError` naming `path` if it cannot be written; a reader
    sees either the old content or the new one, never a partial file.

    ```python
    atomic_write_bytes("model.eqx", buffer.getvalue())
    ```
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise PiezojaxValueError(f"`data` must be bytes, got {type(data).__name__}")
    p = Path(os.fspath(path)).expanduser().absolute()
    try:
        with atomic_file(p) as tmp:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
    except OSError as e:
        raise PiezojaxValueError(f"cannot write {str(p)!r}: {_describe_os_error(e)}") from e
    return p


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write `text` to `path` atomically (see `atomic_write_bytes`).

    **Arguments:**

    - `path`: destination file.
    - `text`: the string to write.
    - `encoding`: text encoding, UTF-8 by default.

    **Returns:**

    The absolute `Path` written.

    ```python
    atomic_write_text("report.md", "# Fit report\\n")
    ```
    """
    if not isinstance(text, str):
        raise PiezojaxValueError(f"`text` must be a str, got {type(text).__name__}")
    return atomic_write_bytes(path, text.encode(encoding))


_RENAME_EXCHANGE = 2  # linux/fs.h


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths with renameat2(RENAME_EXCHANGE) where the OS offers it (Linux ≥ 3.15)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    rc = renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE)
    return rc == 0


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, overwrite: bool = False, kind: str | None = None) -> Iterator[Path]:
    """Context manager yielding a temporary sibling directory that becomes `path` on normal exit.

    Write every output file of a run into the yielded directory. On normal exit it is renamed to `path`. If `path`
    already exists, that is an error (raised on entry, before any work) unless `overwrite=True`; then the two are
    swapped — atomically with `renameat2(RENAME_EXCHANGE)` on Linux, otherwise by two renames with the old directory
    parked at a hidden sibling in between — so at every instant at least one complete version exists on disk, and the
    old one is deleted only after the new one is in place. On any exception (including `KeyboardInterrupt`) the
    temporary directory is removed and `path` is left as it was.

    Never replaced, whatever `overwrite` says: the working directory, a directory containing it, and the home
    directory. With `kind`, the new folder gets a marker file (`MARKER`) recording it and the files written, and
    `overwrite` replaces only a folder whose marker records the same `kind` (a previous output of the same command)
    and which holds nothing else than those files: a file a user put there afterwards is never deleted (the run is
    refused on entry, naming it; one added while the run computes is kept with the previous folder, moved to
    `NAME.previous`, and an `OutputWarning` says so). File browsers' metadata (`.DS_Store`, `Thumbs.db`,
    `desktop.ini`, `._*`) does not count; a marker from a version before the lists lets the folder be replaced as
    it is. An empty directory is replaced like an absent one.
    Temporaries left by killed runs next to `path` are removed on entry; if a live process is writing `path`, entry
    fails.

    **Arguments:**

    - `path`: the output directory to create or replace.
    - `overwrite`: allow replacing an existing directory at `path`.
    - `kind`: what the folder holds (e.g. `"fit"`), for the marker; `None`: no marker, and `overwrite` may replace
      any directory that is not protected.

    **Returns:**

    A context manager yielding the temporary directory as a `Path`.

    ```python
    with atomic_directory("runs/fit-01", overwrite=True) as d:
        save_json(d / "result.json", result)
    ```
    """
    p = check_writable(path)
    check_replaceable_directory(p, overwrite, kind)
    _claim(p)
    tmp = Path(tempfile.mkdtemp(dir=p.parent, prefix=_temp_prefix(p.name)))
    try:
        # mkdtemp makes 0700 directories; give the result the mode a plain mkdir would.
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        if kind is not None:
            from piezojax import __version__

            save_json(tmp / MARKER, {"written_by": "piezojax", "kind": kind, "version": __version__,
                                     "files": _folder_entries(tmp)})
        if p.exists() and not p.is_dir():
            raise PiezojaxValueError(
                f"cannot create directory {str(p)!r}: a file of that name was created by another program while this "
                "run was computing; nothing was replaced and this run's outputs were discarded"
            )
        if not p.exists():
            try:
                os.rename(tmp, p)
            except OSError as e:
                if p.exists():
                    raise PiezojaxValueError(
                        f"output directory {str(p)!r} was created by another program while this run was computing; "
                        "nothing was replaced and this run's outputs were discarded"
                    ) from e
                raise PiezojaxValueError(f"cannot create directory {str(p)!r}: {_describe_os_error(e)}") from e
        elif not (overwrite or _is_empty_directory(p)):
            raise PiezojaxValueError(
                f"output directory {str(p)!r} was created by another program while this run was computing; nothing "
                "was replaced and this run's outputs were discarded"
            )
        else:
            # what appeared meanwhile must qualify too; what a user added to it is dealt with after the swap
            check_replaceable_directory(p, True, kind, look_for_added=False)
            if _exchange(tmp, p):
                old = tmp  # after the exchange the temporary name holds the old directory
            else:
                old = Path(tempfile.mkdtemp(dir=p.parent, prefix=_temp_prefix(p.name) + "old-"))
                os.rmdir(old)
                try:
                    os.rename(p, old)
                except OSError as e:  # e.g. an immutable folder: nothing has moved
                    raise PiezojaxValueError(
                        f"cannot replace directory {str(p)!r}: {_describe_os_error(e)}; it was left as it was and "
                        "this run's outputs were discarded"
                    ) from e
                try:
                    os.rename(tmp, p)
                except BaseException:
                    os.rename(old, p)
                    raise
            _fsync_directory(p.parent)
            kept = _set_aside(old, p, kind)
            if kept is None:
                shutil.rmtree(old, ignore_errors=True)
            else:
                warnings.warn(f"while this run was computing, files were added to the output folder {str(p)!r} it "
                              f"replaced; that previous folder was kept, as {str(kept)!r}", OutputWarning,
                              stacklevel=3)
            return
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        _raise_full(e, p)
        raise
    _fsync_directory(p.parent)


def _raise_full(e: BaseException, p: Path) -> None:
    """A full disk (or quota) while writing `p`, as an error that names `p` (the system's names no file)."""
    if isinstance(e, OSError) and e.errno in _FULL:
        raise OSError(e.errno, f"{_describe_os_error(e)}: cannot write {str(p)!r} (nothing was written there; free "
                               "some space, or write elsewhere)") from e


def _is_empty_directory(p: Path) -> bool:
    try:
        if not p.is_dir() or p.is_symlink():
            return False
        with os.scandir(p) as entries:
            return next(entries, None) is None
    except OSError:
        return False


def _command(kind: str) -> str:
    """The command whose output a marker's `kind` records: `piezojax fit`, or `python -m experiments.NAME` for a
    reproduction (`kind` "experiments.NAME")."""
    return f"`python -m {kind}`" if kind.startswith("experiments.") else f"`piezojax {kind}`"


def check_replaceable_directory(p: Path, overwrite: bool, kind: str | None, option: str = "overwrite=True", *,
                                 look_for_added: bool = True) -> None:
    """Refuse, before any work, an output directory that must not be created or replaced (see `atomic_directory`);
    `option` is how the caller's user asks to overwrite (`"--overwrite"` on the command line); `look_for_added=False`:
    do not look for what the marker does not list."""
    why = _protected(p)
    if why is not None:
        raise PiezojaxValueError(f"refusing to write the output folder {str(p)!r}: {why}")
    if not p.exists():
        return
    if not p.is_dir():
        raise PiezojaxValueError(f"output folder {str(p)!r} is a file")
    if _is_empty_directory(p):  # nothing to lose (e.g. made with mkdir for this run)
        return
    if kind is None:
        if not overwrite:
            raise PiezojaxValueError(f"output folder {str(p)!r} already exists; pass {option} to replace it")
        return
    refusing = f"refusing to replace {str(p)!r}{'' if overwrite else ', which already exists'}"
    found = read_marker(p)
    if found != kind:
        held = "has no piezojax marker" if found is None else f"holds the output of {_command(found)}"
        raise PiezojaxValueError(
            f"{refusing}: it {held}, and {option} "
            f"replaces only the output of an earlier {_command(kind)} (a folder with the marker file {MARKER}); "
            "remove it yourself or choose another output folder"
        )
    try:
        added = _foreign_entries(p) if look_for_added else None
    except PiezojaxValueError as e:
        raise PiezojaxValueError(f"{refusing}: {e}; remove the folder yourself or choose another output folder") from e
    if added:
        shown = ", ".join(repr(e) for e in added[:5]) + (f" and {len(added) - 5} more" if len(added) > 5 else "")
        raise PiezojaxValueError(
            f"{refusing}: it holds what "
            f"the earlier {_command(kind)}{' or `FitResult.save`' if kind == 'fit' else ''} did not write there "
            f"({shown}), which {option} would delete; move that out of the "
            "folder, or choose another output folder"
        )
    if not overwrite:
        raise PiezojaxValueError(f"output folder {str(p)!r} already exists; pass {option} to replace it")


def to_jsonable(obj: Any, _where: str = "obj") -> Any:
    """Convert `obj` to plain JSON types: numpy/JAX arrays → nested lists, scalars → Python numbers, NaN/±inf → None.

    Mappings become objects (keys converted with `str`), tuples/lists become arrays, `Path` becomes a string.
    Anything else raises `PiezojaxValueError` naming where it sits in `obj`.
    """
    if obj is None or isinstance(obj, bool | str):
        return obj
    if isinstance(obj, int) and not isinstance(obj, bool):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v, f"{_where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v, f"{_where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, np.generic) or hasattr(obj, "__array__"):
        try:
            arr = np.asarray(obj)
        except Exception as e:  # e.g. a tracer: not data
            raise PiezojaxValueError(f"cannot convert {_where} ({type(obj).__name__}) to JSON: {e}") from e
        if arr.dtype.kind == "b":
            return arr.tolist()
        if arr.dtype.kind in "iu":
            return arr.tolist()
        if arr.dtype.kind == "f":
            out = arr.astype(np.float64).tolist()
            return _nan_to_none(out)
        if arr.dtype.kind in "US":
            return arr.astype(str).tolist()
        raise PiezojaxValueError(f"cannot convert {_where} (array of dtype {arr.dtype}) to JSON")
    raise PiezojaxValueError(f"cannot convert {_where} of type {type(obj).__name__} to JSON")


def _nan_to_none(x):
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x if math.isfinite(x) else None


def save_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    """Write `obj` as strict JSON to `path`, atomically.

    numpy and JAX arrays and scalars are converted to (nested) lists and Python numbers; NaN and ±inf, which strict
    JSON cannot hold, are written as `null` (so a failed metric reads back as `None`). See `to_jsonable`.

    **Arguments:**

    - `path`: destination file.
    - `obj`: dicts, lists, tuples, strings, numbers, `None`, numpy/JAX arrays and scalars, `Path`s.
    - `indent`: passed to `json.dumps`.

    **Returns:**

    The absolute `Path` written.

    ```python
    save_json("fit.json", {"rmse": np.float64(1e-7), "params": jnp.ones(3)})
    ```
    """
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)
    return atomic_write_text(path, text + "\n")
