"""Writing outputs: atomically (temporary name, then rename), strict JSON, figures.

Every file rtval writes goes through ``atomic_write``: the content goes to a temporary file
beside the target, is checked (a lost write on a full disk is an error, not a short file),
and is renamed into place.  A failed, interrupted or terminated run leaves neither a partial
file nor its temporary; one killed outright (SIGKILL) leaves a ``.tmp-rtval-TAG-PID-*`` file
that the next write into the same directory from the same host and PID namespace (TAG)
removes once process PID is gone.
"""
from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import signal
import stat
import struct
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

TMP_PREFIX = ".tmp-rtval-"


def _space() -> str:
    """This host's and PID namespace's tag: a PID means a process only within one of them,
    so a temporary is removed as stale only by a run in the same (another container or NFS
    host writing into the same directory may be alive)."""
    import hashlib
    import socket
    try:
        ns = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        ns = 0
    return hashlib.sha1(f"{socket.gethostname()}:{ns}".encode()).hexdigest()[:8]


_SPACE = _space()
_LIVE: set[str] = set()          # this process's temporaries (removed at exit, see cleanup())


def attr_text(value) -> str:
    """A value as a file's text attribute (EXR header, PNG text): UTF-8, a path's bytes that
    are not (Python's surrogate escapes) written as \\xNN, where the encoder raised."""
    return str(value).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


class WriteError(OSError):
    """An output that could not be written; ``str(err)`` is one line naming the target."""
    exit_code = 2

    def __init__(self, path: str, reason: str, hint: str = ""):
        super().__init__(f"{path}: cannot write: {reason}" + (f"; {hint}" if hint else ""))
        self.target = path


_HINTS = {errno.ENOSPC: "free some space or write elsewhere",
          errno.EDQUOT: "free some space or write elsewhere",
          errno.EROFS: "the file system is read-only: write elsewhere",
          errno.EACCES: "no permission: write elsewhere",
          errno.EPERM: "no permission: write elsewhere"}


def _reason(exc: BaseException, tmp: str, path: str) -> tuple[str, str]:
    """(one-line reason, hint) of a failed write, naming ``path`` and never the temporary."""
    code = getattr(exc, "errno", None)
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    else:
        text = (str(exc).splitlines() or [type(exc).__name__])[0]
        for e, name in ((errno.ENOSPC, "No space left on device"),
                        (errno.EDQUOT, "Disk quota exceeded"),
                        (errno.EROFS, "Read-only file system"),
                        (errno.EACCES, "Permission denied")):
            if name.lower() in text.lower():
                code, text = e, name
                break
    text = (text.replace(tmp, path) if tmp else text).rstrip(". ")
    return text[:1].lower() + text[1:], _HINTS.get(code, "")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def left_by_killed_runs(directory: str, prefix: str) -> list[str]:
    """The names in ``directory`` that start PREFIX + PID + '-' where process PID (not this
    one) is gone: what a killed run left."""
    try:
        names = os.listdir(directory)
    except OSError:
        return []
    out = []
    for name in names:
        pid = name[len(prefix):].split("-", 1)[0] if name.startswith(prefix) else ""
        if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            out.append(name)
    return out


def scratch_dir(kind: str) -> str:
    """A new directory ``rtval-KIND-TAG-PID-*`` in the temporary directory, for a run's
    scratch files (a local Dask cluster's, ``check --run``'s images); the ones killed runs
    left (their PID gone, same host and PID namespace TAG) are removed first."""
    import shutil
    base = tempfile.gettempdir()
    mine = f"rtval-{kind}-{_SPACE}-"
    for name in left_by_killed_runs(base, mine):
        shutil.rmtree(os.path.join(base, name), ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{mine}{os.getpid()}-")


KERNELS = "rtval-kernels-"
SPACE_MARK = ".rtval-space"


def claim_kernel_cache() -> None:
    """The empty kernel cache ``rtval bench`` and ``report`` point Dr.Jit at
    (tools/cmd_bench.py ``fresh_kernel_cache``: ``rtval-kernels-PID-*`` in the temporary
    directory, made before Dr.Jit's import, where this module cannot be imported yet) gets
    this host's and PID namespace's tag; those killed runs left (their PID gone, the same
    tag) are removed.  A SIGKILL or the out-of-memory killer left them for good (a review),
    as ``atexit`` removes them."""
    import shutil
    mine = os.environ.get("DRJIT_CACHE_DIR", "")
    if os.path.basename(mine).startswith(f"{KERNELS}{os.getpid()}-"):
        with contextlib.suppress(OSError):
            with open(os.path.join(mine, SPACE_MARK), "w") as f:
                f.write(_SPACE)
    base = tempfile.gettempdir()
    for name in left_by_killed_runs(base, KERNELS):
        try:
            with open(os.path.join(base, name, SPACE_MARK)) as f:
                tag = f.read()
        except OSError:
            continue                    # (not marked: another run's, or not ours to say)
        if tag == _SPACE:
            shutil.rmtree(os.path.join(base, name), ignore_errors=True)


def remove_stale(directory: str) -> list[str]:
    """Remove the temporaries that killed rtval runs left in ``directory`` (their process is
    gone); say so on stderr.  Returns the names removed."""
    removed = []
    for name in left_by_killed_runs(directory, f"{TMP_PREFIX}{_SPACE}-"):
        try:
            os.unlink(os.path.join(directory, name))
            removed.append(name)
        except OSError:
            pass
    if removed:
        print(f"rtval: removed {len(removed)} temporary file(s) left in {directory} by a "
              f"killed run ({', '.join(sorted(removed)[:3])}{', ...' if len(removed) > 3 else ''})",
              file=sys.stderr)
    return removed


_HOLD = {"depth": 0, "pending": []}


@contextmanager
def signals_held():
    """A block during which a signal handler that asks ``held`` defers itself (tools/cli.py's
    SIGTERM and SIGHUP handler): a temporary is created and registered in _LIVE with no
    handler raising in between, where the file would exist under a name nobody knows.  The
    deferred signal is raised again when the block ends.  (Ctrl-C keeps Python's own
    handler: a KeyboardInterrupt in that window can still leave one temporary, which the
    next run's ``remove_stale`` removes once this process is gone.)"""
    _HOLD["depth"] += 1
    try:
        yield
    finally:
        _HOLD["depth"] -= 1
        if not _HOLD["depth"] and _HOLD["pending"]:
            signum = _HOLD["pending"][0]
            _HOLD["pending"].clear()
            signal.raise_signal(signum)


def held(signum: int) -> bool:
    """For a signal handler: True while a ``signals_held`` block runs (the signal is then
    raised again at its end), else False."""
    if _HOLD["depth"] and threading.current_thread() is threading.main_thread():
        _HOLD["pending"].append(signum)
        return True
    return False


def cleanup() -> None:
    """Remove this process's temporaries (on SIGTERM and at exit; writes in progress die)."""
    for tmp in list(_LIVE):
        try:
            os.unlink(tmp)
        except OSError:
            pass
        _LIVE.discard(tmp)


def _checked(write, tmp: str, path: str, verify) -> None:
    """``write(tmp)``, then ``verify(tmp)``; any failure becomes one WriteError naming
    ``path``."""
    try:
        write(tmp)
        size = os.path.getsize(tmp)
        problem = "the file came out empty" if size == 0 else (verify(tmp) if verify else None)
    except WriteError:
        raise
    except (OSError, RuntimeError, ValueError, struct.error) as exc:
        # (the EXR binding raises RuntimeError; a verify that misreads a damaged file,
        # struct.error or ValueError: either way the write did not succeed)
        reason, hint = _reason(exc, tmp, path)
        raise WriteError(path, reason, hint) from None
    if problem:
        free = free_bytes(os.path.dirname(tmp))
        if free is not None and free < (1 << 20):
            raise WriteError(path, f"no space left on device ({problem})",
                             _HINTS[errno.ENOSPC])
        raise WriteError(path, problem)


def free_bytes(directory: str) -> int | None:
    """The bytes an unprivileged process may still write in ``directory``'s file system, or
    None where it cannot be asked."""
    try:
        st = os.statvfs(directory)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def _copy_into(src: str, path: str) -> None:
    """Copy ``src`` into an existing non-regular file (a device, a pipe), every write
    checked."""
    try:
        with open(src, "rb") as f, open(path, "wb", buffering=0) as out:
            while chunk := f.read(1 << 20):
                view = memoryview(chunk)
                while view:
                    n = out.write(view)
                    view = view[n:]
    except OSError as exc:
        reason, hint = _reason(exc, src, path)
        raise WriteError(path, reason, hint) from None


def atomic_write(path: str, write, verify=None) -> None:
    """Call ``write(tmp_path)`` and rename the result to ``path`` only if it succeeded and
    ``verify(tmp_path)`` (if given) returns no problem.

    A symlink is written through (its target is replaced); an existing non-regular file
    (``/dev/null``, a pipe) gets the bytes copied in with every write checked; the new file
    gets the mode of the file it replaces, or 0666 less the umask.  Failures raise
    WriteError (one line naming ``path``); no temporary is left behind."""
    shown = os.fspath(path)
    if os.path.isdir(shown):
        raise IsADirectoryError(errno.EISDIR, "is a directory, expected a file name", shown)
    from .inputfile import was_read
    if was_read(shown):         # (a scene's texture under --ppm textures/x.ppm, say)
        raise WriteError(shown, "it is a file this command read", "write the output elsewhere")
    ext = os.path.splitext(shown)[1]
    if os.path.exists(shown) and not os.path.isfile(shown):
        with tempfile.TemporaryDirectory(prefix=f"rtval-{os.getpid()}-") as d:
            tmp = os.path.join(d, "out" + ext)
            _checked(write, tmp, shown, verify)
            _copy_into(tmp, shown)
        return
    path = os.path.realpath(shown)
    directory = os.path.dirname(path)
    created, d = [], directory              # the directories this write creates, deepest first
    while d and not os.path.exists(d) and d != os.path.dirname(d):
        created.append(d)
        d = os.path.dirname(d)
    try:
        os.makedirs(directory, exist_ok=True)
    except FileExistsError:
        raise NotADirectoryError(errno.ENOTDIR, "not a directory", directory) from None
    except OSError as exc:
        raise WriteError(shown, f"cannot create {directory} ({(exc.strerror or str(exc)).lower()})") from None
    tmp = fd = None
    try:                                    # (stopped before the write: the directories go)
        remove_stale(directory)
        if os.path.exists(path):
            mode = stat.S_IMODE(os.stat(path).st_mode)
        else:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        with signals_held():
            try:
                fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{_SPACE}-{os.getpid()}-",
                                           suffix=ext, dir=directory)
            except OSError as exc:
                reason, hint = _reason(exc, "", shown)
                raise WriteError(shown, reason, hint) from None
            _LIVE.add(tmp)
        os.close(fd)
        fd = None
    except BaseException:
        if fd is not None:
            os.close(fd)
        if tmp is not None:                 # (a signal held while it was made)
            _LIVE.discard(tmp)
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        _remove_dirs(created)
        raise
    done = staged = False
    try:
        _checked(write, tmp, shown, verify)
        os.chmod(tmp, mode)
        if _BATCH:                          # inside together(): renamed at its end
            _BATCH[-1].append((tmp, path, created, shown))
            staged = True
        else:
            _rename(tmp, path, shown)
        done = True
    finally:
        if not staged:
            _LIVE.discard(tmp)
            if os.path.lexists(tmp):
                os.unlink(tmp)
        if not done:
            _remove_dirs(created)


_BATCH: list = []   # the open together() blocks: their staged (tmp, path, created, shown)


@contextlib.contextmanager
def together():
    """The atomic_writes inside the block are all renamed into place at its end, or none is:
    each writes and checks its temporary as usual, and the renames wait until the block has
    finished without an exception (a command with several outputs, or a scene with its side
    files, leaves all of them or nothing).  Writes into a device or a pipe are not held."""
    _BATCH.append([])
    ok = False
    try:
        yield
        ok = True
    finally:
        staged = _BATCH.pop()
        if ok and _BATCH:                   # nested: the outer block decides
            _BATCH[-1].extend(staged)
        elif ok:
            # (a rename can still fail, e.g. a file of another user in a sticky directory:
            # then the temporaries not yet renamed go, and the error is one line)
            for k, (tmp, path, _, shown) in enumerate(staged):
                try:
                    _rename(tmp, path, shown)
                except WriteError:
                    _discard(staged[k:])
                    raise
                _LIVE.discard(tmp)
        else:
            _discard(staged)


def _rename(tmp: str, path: str, shown: str) -> None:
    """Put a written temporary in place; a failure (e.g. a file of another user in a sticky
    directory) is one WriteError naming the output as the user gave it."""
    try:
        os.replace(tmp, path)
    except OSError as exc:
        reason, hint = _reason(exc, tmp, shown)
        raise WriteError(shown, reason, hint) from None


def _discard(staged) -> None:
    """Remove staged temporaries and the directories their writes created."""
    for tmp, _, created, _ in reversed(staged):
        _LIVE.discard(tmp)
        if os.path.lexists(tmp):
            os.unlink(tmp)
        _remove_dirs(created)


def _remove_dirs(created: list) -> None:
    """Remove the directories a failed write created, deepest first, while empty."""
    for d in created:
        try:
            os.rmdir(d)
        except OSError:
            break


def _probe(directory: str, shown: str) -> None:
    """Can a file be created in ``directory`` (permissions, read-only or pseudo file
    systems such as /proc)?  A WriteError naming ``shown`` if not."""
    # (named like every temporary, and made under signals_held: one a kill leaves behind
    # is found and removed by remove_stale like the others)
    with signals_held():
        try:
            fd, probe = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{_SPACE}-{os.getpid()}-",
                                         dir=directory)
        except OSError as e:
            reason = (e.strerror or str(e)).lower()
            raise WriteError(shown, f"cannot create a file in {directory} ({reason})",
                             _HINTS.get(e.errno, "write elsewhere")) from None
        os.close(fd)
        os.unlink(probe)


def _existing_parent(path: str, shown: str) -> str:
    """The nearest existing directory at or above ``path`` (which atomic_write would create
    the rest below); a WriteError if that is not a directory."""
    d = os.path.abspath(path)
    while not os.path.exists(d) and d != os.path.dirname(d):
        d = os.path.dirname(d)
    if not os.path.isdir(d):
        raise WriteError(shown, f"{d} is not a directory")
    return d


def check_file_target(path: str, make_dirs: bool = True) -> None:
    """Refuse, before any work, an output file that cannot be written: a directory, a
    missing directory (unless ``make_dirs``: atomic_write creates it), a file below a
    non-directory, or a place where no file can be created.  An existing non-regular file
    (/dev/null, a pipe) is written through and not probed."""
    from .usererror import InputError
    shown = os.fspath(path)
    if os.path.isdir(shown):
        raise InputError(f"{shown}: is a directory; give a file name")
    if os.path.exists(shown) and not os.path.isfile(shown):
        return
    parent = os.path.dirname(os.path.abspath(shown))
    if not make_dirs and not os.path.exists(parent):
        # a typo in a directory name should not become a new directory tree
        raise InputError(f"{shown}: no directory {parent}; create it first")
    _probe(_existing_parent(parent, shown), shown)


def check_dir_target(path: str) -> None:
    """Refuse, before any work, an output directory that cannot be made or written into:
    an existing file, a path below a non-directory, or a place where no file can be
    created."""
    shown = os.fspath(path)
    if os.path.exists(shown) and not os.path.isdir(shown):
        raise WriteError(shown, "is not a directory", "give a directory, or a new name")
    _probe(_existing_parent(shown, shown), shown)


def jsonable(x):
    """NaN and ±Inf become the strings "nan", "inf", "-inf", so that JSON stays strict."""
    if isinstance(x, float) and not math.isfinite(x):
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    return x


def json_text(data, indent: int = 1) -> str:
    return json.dumps(jsonable(data), indent=indent, allow_nan=False) + "\n"


def write_json(path: str, data, indent: int = 1) -> None:
    text = json_text(data, indent)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def save_figure(fig, path: str, provenance: dict | None = None, **kw) -> None:
    """A matplotlib figure as PNG, atomically, with provenance in its text chunks."""
    meta = {k: str(v) for k, v in (provenance or {}).items()}
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", metadata=meta, **kw))
