"""Outputs that never destroy what they did not create (INTERFACES.md section 3).

1. `prepare_output(path, force=..., inputs=..., kind=...)`, BEFORE any work, refuses with
   an OutputError (one line naming the option, the path and the problem; exit 2): `.`, `..`,
   the working directory or its parents; an output that is, holds or lies inside an input
   of the run (even with --force); an existing output without --force, or one that is not a
   previous output of ours (even with --force); an output that cannot be written (probed).
   `prepare_outputs_in(directory, names, ...)`: the same for named files in a directory.
   It also claims the output (flock on `.NAME.egovib-lock` beside it, held until
   `release_outputs()`): a second run is refused at once, naming the run that holds it,
   rather than made to wait and then find the output there (or replace it with --force).
2. `atomic_output(path, directory=...)`: the output is written in a hidden staging
   directory beside its target (`.NAME.PID.XXXX.partial`) and renamed into place only when
   the block succeeds; an existing target only if of the same type and, for a directory,
   ours (its MARKER file lists the files we wrote). A full file system (quota, size limit,
   turned read-only) is an OutputError naming the output and the free space.

Staging directories of killed runs are removed by the next run writing beside them: only
ours (PARTIAL_MARKER), only older than this process, only when their process is gone.
"""

from __future__ import annotations

import atexit
import contextlib
import datetime as _dt
import errno
import fcntl
import json
import os
import re
import secrets
import shutil
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from egovib_ros import __version__
from egovib_ros.errors import EgovibError

MARKER = ".egovib-output"  # JSON marker inside every directory output we write
#: The keys of a --truth file (`egovib simulate`, the alternate reality)
TRUTH_KEYS = ("seed", "effects", "tap_onsets_ns")
MARKER_SCHEMA = "egovib.output/1"
PARTIAL_SUFFIX = ".partial"
PARTIAL_MARKER = ".egovib-partial"  # JSON {pid, created} inside every staging directory
LOCK_SUFFIX = ".egovib-lock"  # `.NAME.egovib-lock` beside an output: flocked while a run claims it
# A write failing with these means the output's file system cannot take it (not bad code).
_WRITE_FULL = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large for the file system",
    errno.EROFS: "the file system became read-only",
}
MODEL_SCHEMA = "egovib.noise_model"

# kind -> what the output is; directories and files never replace each other.
DIRECTORY_KINDS = ("bag", "report", "directory")
FILE_KINDS = ("model", "json", "file")

_PARTIAL = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[0-9a-f]{8}\.partial$")


class OutputError(EgovibError):
    """An output path is refused: it exists, is an input, is not ours, or cannot be written."""


# --- checks done before any work ---------------------------------------------------------
def prepare_output(
    path: str | os.PathLike,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike | None] = (),
    kind: str = "file",
    option: str = "--out",
    ours: Callable[[Path], bool] | None = None,
) -> Path:
    """`path` as a Path if this run may write it, else OutputError (one line); claims it and
    removes our stale staging directories beside it.

    inputs: paths this run reads (and its other outputs). kind: "bag" | "report" |
    "directory" (directories) or "model" | "json" | "file": with --force an existing output
    is replaced only if it is a previous output of ours of that type (`_why_not_ours`);
    `ours(path)` tells a file this command wrote from another of that type (a user's CSV)."""
    if kind not in DIRECTORY_KINDS + FILE_KINDS:
        raise ValueError(f"unknown output kind {kind!r}")
    label = f"{option} {path}"
    target = _check_path_itself(path, label)
    _check_not_an_input(target, inputs, label)
    _check_existing(target, force, kind, label, ours)
    _check_writable(target, label)
    claim_output(target, label)
    try:  # again under the lock: a run that held it may have written the output meanwhile
        _check_existing(target, force, kind, label, ours)
    except OutputError:
        release_outputs(target)
        raise
    clean_stale_partials(target.parent)
    return target


def _check_existing(target: Path, force: bool, kind: str, label: str, ours) -> None:
    if os.path.lexists(target):
        if not force:
            raise OutputError(f"{label}: already exists (use --force to replace it)")
        reason = _why_not_ours(target, kind)
        if reason is None and ours is not None and not _safely(ours, target):
            reason = "is not an output of this command"
        if reason:
            raise OutputError(f"{label}: {reason}; not replaced, even with --force")


def prepare_outputs_in(
    directory: str | os.PathLike,
    names: Sequence[str],
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike | None] = (),
    option: str = "--out",
) -> Path:
    """Like prepare_output for a command that writes the files `names` into `directory`: the
    directory may exist (it is added to, never replaced); each named file that exists needs
    --force, and must then be a regular file (.json files: JSON)."""
    label = f"{option} {directory}"
    target = _check_path_itself(directory, label)
    _check_not_an_input(target, inputs, label)
    if os.path.lexists(target) and not target.is_dir():
        raise OutputError(f"{label}: exists and is not a directory")
    existing = [name for name in names if os.path.lexists(target / name)]
    if existing and not force:
        raise OutputError(f"{label}: already holds {', '.join(existing)} (use --force to replace)")
    for name in existing:
        reason = _why_not_ours(target / name, "json" if name.endswith(".json") else "file")
        if reason:
            raise OutputError(f"{label}: {name}: {reason}; not replaced, even with --force")
    _check_writable(target / (names[0] if names else "x"), label)
    claim_output(target, label)
    if target.is_dir():
        clean_stale_partials(target)
    return target


def _check_path_itself(path: str | os.PathLike, label: str) -> Path:
    text = os.fspath(path)
    if not text.strip():
        raise OutputError(f"{label or 'output'}: empty path")
    target = Path(text)
    # Path drops a trailing "/." ("a/." is "a"): the text says it
    if target.name in ("", ".", "..") or text.rstrip("/").endswith(("/.", "/..")):
        raise OutputError(
            f"{label}: refusing to write to '.' or '..'; name a new file or directory"
        )
    resolved = _resolve(target)
    cwd = _resolve(Path.cwd())
    if resolved == cwd or resolved in cwd.parents or resolved == Path(resolved.anchor):
        raise OutputError(
            f"{label}: is the working directory or one of its parents; name a new file or directory"
        )
    return target


def _resolve(path: Path) -> Path:
    """Absolute path with symlinks resolved as far as the path exists."""
    return Path(os.path.realpath(os.path.abspath(path)))


def _check_not_an_input(
    target: Path, inputs: Iterable[str | os.PathLike | None], label: str
) -> None:
    out = _resolve(target)
    for item in inputs:
        if item is None or not os.fspath(item):
            continue
        src = _resolve(Path(item))
        same = out == src
        if not same and os.path.exists(target) and os.path.exists(item):
            with contextlib.suppress(OSError):
                same = os.path.samefile(target, item)  # hard links, bind mounts
        if same:
            raise OutputError(f"{label}: is {item}, an input of this run; refusing to overwrite it")
        if src in out.parents:
            raise OutputError(
                f"{label}: lies inside {item}, an input of this run; write it elsewhere"
            )
        if out in src.parents:
            raise OutputError(
                f"{label}: holds {item}, an input of this run; refusing to replace it"
            )


def _check_writable(target: Path, label: str) -> None:
    """Create (and remove) a probe file holding one block where the output will be written:
    a full file system is refused here, before any work."""
    parent = _resolve(target).parent
    ancestor = parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(f"{label}: {ancestor} is not a directory")
    probe = None
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".probe", dir=ancestor)
        try:
            os.write(fd, bytes(4096))
        finally:
            os.close(fd)
    except OSError as exc:
        reason = "read-only file system" if exc.errno == errno.EROFS else (exc.strerror or str(exc))
        raise OutputError(f"{label}: cannot write in {ancestor} ({reason})") from None
    finally:
        if probe is not None:
            with contextlib.suppress(OSError):
                os.unlink(probe)


# --- a stop requested by a signal ------------------------------------------------------------
_STOP: list[type[BaseException]] = []


def request_stop(exception: type[BaseException]) -> None:
    """Record that the run must stop (the CLI's Ctrl-C and SIGTERM handlers, before raising
    `exception`): a library that swallows the exception (a bare `except:`, C code clearing
    the error) cannot make the run commit an output: `atomic_output` raises it again."""
    if not _STOP:
        _STOP.append(exception)


def clear_stop() -> None:
    _STOP.clear()


# --- one run per output ----------------------------------------------------------------------
# resolved target -> (lock file, its descriptor, directories made for it: removed if empty)
_CLAIMS: dict[Path, tuple[Path, int, list[Path]]] = {}


def claim_output(target: str | os.PathLike, label: str = "") -> None:
    """Lock the output `target` for this run: `.NAME.egovib-lock` beside it, flocked
    (released by the kernel if the process dies, whatever kills it); held by another
    process: OutputError naming its pid. A claim this process holds already is kept."""
    key = _resolve(Path(target))
    if key in _CLAIMS:
        return
    label = label or str(target)
    made = _make_parents(key.parent, label)
    lock_path = key.parent / f".{key.name}{LOCK_SUFFIX}"
    try:
        while True:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = _lock_holder(fd)
                os.close(fd)
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise OutputError(
                        f"{label}: cannot lock {lock_path} ({exc.strerror})"
                    ) from None
                raise OutputError(
                    f"{label}: another egovib run{holder} is writing it; wait for it to end "
                    f"or choose another output"
                ) from None
            # The run that held it removes the lock file as it ends: lock the file that is
            # there now, not one already unlinked.
            try:
                here = os.stat(lock_path)
                mine = os.fstat(fd)
                if (here.st_dev, here.st_ino) == (mine.st_dev, mine.st_ino):
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
    except OSError as exc:
        _remove_empty(made)
        raise OutputError(f"{label}: cannot create {lock_path} ({exc.strerror})") from None
    except BaseException:
        _remove_empty(made)
        raise
    with contextlib.suppress(OSError):  # only for the message of a run refused; may not fit
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    _CLAIMS[key] = (lock_path, fd, made)


def release_outputs(*targets: str | os.PathLike) -> None:
    """Release the claims on `targets` (all claims of this process if none given): the lock
    file is removed, then unlocked; directories made for it go if empty."""
    keys = [_resolve(Path(t)) for t in targets] if targets else list(_CLAIMS)
    for key in keys:
        if key not in _CLAIMS:
            continue
        lock_path, fd, made = _CLAIMS.pop(key)
        with contextlib.suppress(OSError):
            os.unlink(lock_path)
        os.close(fd)
        _remove_empty(made)


atexit.register(release_outputs)


def _lock_holder(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return ""
    return f" (pid {text})" if text.isdigit() else ""


def _make_parents(directory: Path, label: str) -> list[Path]:
    missing = []
    while not directory.exists():
        missing.append(directory)
        directory = directory.parent
    made = []
    try:
        for path in reversed(missing):
            path.mkdir()
            made.append(path)
    except OSError as exc:
        _remove_empty(made)
        raise OutputError(f"{label}: cannot create {path} ({exc.strerror})") from None
    return made


def _remove_empty(directories: list[Path]) -> None:
    for path in reversed(directories):
        with contextlib.suppress(OSError):
            path.rmdir()


# --- what counts as ours -----------------------------------------------------------------
def json_holding(keys: Iterable[str] = (), **values) -> Callable[[Path], bool]:
    """`ours` for prepare_output: a JSON object with these keys, and these values."""

    def ours(path: Path) -> bool:
        body = json.loads(path.read_text())
        return (
            isinstance(body, dict)
            and set(keys) <= set(body)
            and all(body.get(k) == v for k, v in values.items())
        )

    return ours


def text_starting_with(first_line: str) -> Callable[[Path], bool]:
    """`ours` for prepare_output: a text file whose first line is `first_line`."""

    def ours(path: Path) -> bool:
        with open(path, encoding="utf-8") as fh:  # a file without newlines is not read whole
            return fh.readline(len(first_line) + 2).rstrip("\r\n") == first_line

    return ours


def _safely(ours: Callable[[Path], bool], path: Path) -> bool:
    try:
        return bool(ours(path))
    except Exception:  # an unreadable or odd file is not ours
        return False


def _why_not_ours(path: Path, kind: str) -> str | None:
    """None if `path` is a previous output of ours that an output of `kind` may replace,
    else a short reason."""
    if kind in DIRECTORY_KINDS:
        if path.is_symlink() or not path.is_dir():
            return "exists and is not a directory"
        return _why_not_our_directory(path, kind)
    if path.is_dir():
        return "is a directory"
    if kind == "model":
        return None if _is_our_model(path) else "is not an egovib noise model"
    if kind == "json":
        try:
            json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError):
            return "is not a JSON file"
    return None


def _why_not_our_directory(path: Path, kind: str | None) -> str | None:
    files = _relative_files(path)
    marker = _read_json(path / MARKER)
    if isinstance(marker, dict) and marker.get("schema") == MARKER_SCHEMA:
        ours = set(marker.get("files", [])) | {MARKER}
        foreign = sorted(f for f in files if f not in ours)
        if foreign:
            return f"holds files egovib did not write ({_short_list(foreign)})"
        # A bag is recorded data: only a bag replaces it, and a bag replaces only a bag (a
        # bag_recorder's bag is marked "directory": its metadata.yaml tells it)
        was_bag = marker.get("kind") == "bag" or "metadata.yaml" in files
        holds = set(files) - {MARKER}  # (an empty one loses nothing)
        if kind is not None and holds and was_bag != (kind == "bag"):
            return "is a bag egovib wrote" if was_bag else "is an egovib output but not a bag"
        return None
    if not files:
        return None  # an empty directory loses nothing
    return f"is not an egovib output (no {MARKER} marker; holds {_short_list(sorted(files))})"


def _is_our_model(path: Path) -> bool:
    try:
        with zipfile.ZipFile(path) as zf:
            if "schema.npy" not in zf.namelist():
                return False

        with np.load(path, allow_pickle=False) as data:
            return str(data["schema"]) == MODEL_SCHEMA
    except Exception:  # any unreadable file is not ours
        return False


def _relative_files(path: Path) -> list[str]:
    out = []
    for root, dirs, names in os.walk(path):
        for name in names + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            out.append(os.path.relpath(os.path.join(root, name), path))
    return out


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None


def _short_list(items: list[str], limit: int = 3) -> str:
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


# --- writing -------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike, *, directory: bool = False, kind: str | None = None
) -> Iterator[Path]:
    """Yield a temporary sibling path; move it onto `path` only if the block succeeds.

    With `directory=True` (bags, report directories) the path does not exist yet (writers
    that create their directory themselves can); the marker listing its files is added
    before the move. An existing `path` is replaced only if of the same type and, for a
    directory, ours; else OutputError and the new output is discarded."""
    final = Path(path)
    parent = final.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{final}: cannot create {parent} ({exc.strerror})") from None
    clean_stale_partials(parent)
    staging = _make_staging(parent, final.name)
    tmp = staging / final.name
    try:
        yield tmp
        if _STOP:  # Ctrl-C or SIGTERM came, and something swallowed what they raised
            raise _STOP[0]()
        if directory and tmp.is_dir():
            _write_marker(tmp, kind)
        _move_into_place(tmp, final, directory=directory, kind=kind, staging=staging)
    except OSError as exc:
        if exc.errno not in _WRITE_FULL:
            raise
        where = f"{_resolve(parent)}{_free_space(parent)}"
        raise OutputError(f"{final}: not written: {_WRITE_FULL[exc.errno]} in {where}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _free_space(directory: Path) -> str:
    """' (N MB free)' for the file system of `directory`, '' if unknown."""
    try:
        st = os.statvfs(directory)
    except OSError:
        return ""
    return f" ({st.f_bavail * st.f_frsize / 1e6:.1f} MB free)"


def _make_staging(parent: Path, name: str) -> Path:
    staging = parent / f".{name}.{os.getpid()}.{secrets.token_hex(4)}{PARTIAL_SUFFIX}"
    try:
        staging.mkdir()
        (staging / PARTIAL_MARKER).write_text(
            json.dumps({"pid": os.getpid(), "created": time.time()})
        )
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)  # made, but its marker did not fit
        raise OutputError(f"{parent / name}: cannot write in {parent} ({exc.strerror})") from None
    return staging


def _write_marker(directory: Path, kind: str | None) -> None:
    files = sorted(_relative_files(directory))
    marker = {
        "schema": MARKER_SCHEMA,
        "kind": kind or "directory",
        "files": files,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "software_version": __version__,
    }
    (directory / MARKER).write_text(json.dumps(marker, indent=1) + "\n")


def check_replaceable(
    path: str | os.PathLike, *, directory: bool = False, kind: str | None = None
) -> None:
    """OutputError now, before any work, if `atomic_output(path, directory=..., kind=...)`
    would refuse to replace what is there at the end."""
    final = Path(path)
    if not os.path.lexists(final):
        return
    if not directory:
        reason = "is a directory" if final.is_dir() else None
    elif final.is_symlink() or not final.is_dir():
        reason = "exists and is not a directory"
    else:
        reason = _why_not_our_directory(final, kind)
    if reason:
        raise OutputError(f"{final}: {reason}; not replaced")


def _move_into_place(
    tmp: Path, final: Path, *, directory: bool, kind: str | None, staging: Path
) -> None:
    check_replaceable(final, directory=directory, kind=kind)
    if not directory or not os.path.lexists(final):
        os.replace(tmp, final)
        return
    # Old output aside first, new one in, then the old one goes: never neither.
    old = staging / ".replaced"
    os.replace(final, old)
    try:
        os.replace(tmp, final)
    except OSError:
        os.replace(old, final)
        raise


# --- stale staging directories -----------------------------------------------------------
def clean_stale_partials(directory: str | os.PathLike) -> list[Path]:
    """Remove our own staging directories (PARTIAL_MARKER inside) in `directory` older
    than this process whose process is gone; returns what was removed."""
    removed = []
    try:
        entries = list(Path(directory).iterdir())
    except OSError:
        return removed
    started = process_start_time()
    for entry in entries:
        named = _PARTIAL.match(entry.name)
        if not named or entry.is_symlink() or not entry.is_dir():
            continue
        try:
            if _is_stale_partial(entry, int(named["pid"]), started):
                shutil.rmtree(entry)
                removed.append(entry)
        except OSError:
            continue  # read-only or racing: leave it
    return removed


def _is_stale_partial(entry: Path, named_pid: int, started: float) -> bool:
    marker = _read_json(entry / PARTIAL_MARKER)
    if isinstance(marker, dict):
        pid, created = marker.get("pid"), marker.get("created")
        if not isinstance(pid, int) or not isinstance(created, (int, float)):
            return False
    else:
        # A run killed (SIGKILL) between making the directory and writing its marker: empty
        # but for an empty marker, so nothing is lost with it; its pid is in its name.
        contents = [p.name for p in entry.iterdir()]
        empty = contents == [] or (
            contents == [PARTIAL_MARKER] and (entry / PARTIAL_MARKER).stat().st_size == 0
        )
        if not empty:
            return False
        pid, created = named_pid, entry.stat().st_mtime
    return created < started and not _pid_alive(pid)


def clean_partials_of(directory: str | os.PathLike, pids: Iterable[int]) -> list[Path]:
    """Remove the staging directories in `directory` of the processes `pids` once they are
    gone (the workers of a parallel run stopped mid-bag: bag.many); returns them."""
    pids, removed = set(pids), []
    with contextlib.suppress(OSError):
        for entry in Path(directory).iterdir():
            named = _PARTIAL.match(entry.name)
            if (
                named
                and int(named["pid"]) in pids
                and not _pid_alive(int(named["pid"]))
                and not entry.is_symlink()
                and (entry / PARTIAL_MARKER).is_file()
            ):
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry)
    return removed


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True


_IMPORT_TIME = time.time()


def process_start_time() -> float:
    """Wall-clock start of this process, to a clock tick (Linux /proc: now minus the time
    since it started; /proc/stat's boot time is whole seconds, which made a run started
    within a second of a killed one take that run's staging for its own age), else when
    this module was imported."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        ticks = int(fields[19])  # field 22: starttime, clock ticks after boot
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return time.time() - (uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return _IMPORT_TIME
