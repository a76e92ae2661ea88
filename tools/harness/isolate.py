"""One benchmark case in a Python process of its own (``rtval bench``'s default, every mode
but ``--command``, which starts a process per run anyway).

In one process a case's times depended on the cases before it (primary rays, 1920 columns,
same commit: spheres 16's rt_core float32 took 3.80 ms after the finite-plane cases, 3.40 ms
on its own, while Mitsuba's 7.78 and 7.98 ms stayed within its spread; the cause is not
found: docs/speed.md, "Each case in a process of its own").

The child first runs a small warm-up case of the same function (``warm``, another scene kind
than the case's, so that none of the case's own kernels is made there): what the first case
of a run in one process paid once (Dr.Jit's LLVM back end, Mitsuba's variant and plugins, its
scene-independent kernels) is then paid before the measured case, not inside its first call.
It writes the case's JSON, with the process's ``pid`` and Dr.Jit's thread count, to a file in
a temporary folder, which the parent reads and removes.  A child that fails ends the run with
one line: its error's, which it writes to a file beside the JSON (what a library prints at
exit may follow it on stderr), or the signal that killed it.  The child dies with its parent:
killed by the parent when a signal ends it, and by the kernel's parent-death signal when the
parent is killed outright.  The temporary folder is ``rtval-case-TAG-PID-*``: one a killed
run left is removed by the next (``rt_core.outputs.scratch_dir``).

    python -m tools.harness.isolate SPEC.json OUT.json   (the child; SPEC from ``run_case``)
"""
from __future__ import annotations

import contextlib
import importlib
import json
import os
import signal
import subprocess
import sys
import tempfile

from tools.harness.pipes import Tail

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run_case(label: str, module: str, function: str, kwargs: dict, warm: dict | None = None,
             threads: int | None = None) -> dict:
    """``module.function(**kwargs)`` (a JSON-able dict) in a new Python process, after
    ``module.function(**warm)`` there; ``threads``: Dr.Jit's worker threads there.  A
    failure raises InputError: the child's exit code where it said why (a user's error: its
    code; a bug, or no result: 1), 128 + the signal's number where a signal killed it.  What
    the child says on stderr is passed on (its last 16 KiB)."""
    import shutil
    from rt_core.outputs import scratch_dir
    from rt_core.usererror import InputError
    spec = {"module": module, "function": function, "kwargs": kwargs, "warm": warm,
            "threads": threads, "parent": os.getpid()}
    d = None
    try:
        # (rtval-case-TAG-PID-*: the ones killed runs left are removed by the next)
        d = scratch_dir("case")
        spec_path, out = os.path.join(d, "spec.json"), os.path.join(d, "case.json")
        with open(spec_path, "w") as f:
            json.dump(spec, f)
    except OSError as e:
        if d is not None:
            shutil.rmtree(d, ignore_errors=True)
        raise InputError(f"{label}: cannot write its files in {tempfile.gettempdir()}: "
                         f"{(e.strerror or str(e)).lower()}; free some space there or set "
                         "TMPDIR to a folder that has some") from None
    try:
        p = said = None
        try:
            p = subprocess.Popen([sys.executable, "-m", "tools.harness.isolate", spec_path,
                                  out], cwd=REPO, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.PIPE)
            said = Tail(p.stderr)       # (its last lines only: a case may print a lot)
            code = p.wait()
        except BaseException:           # a signal, Ctrl-C: the case ends with the run
            if p is not None:
                p.kill()
                p.wait()
            raise
        finally:
            if said is not None:
                said.stop()
        if code == 0 and os.path.exists(out):
            if said.buf.strip():        # (its warnings, as in one process)
                sys.stderr.write(said.buf.decode("utf-8", "replace"))
            with open(out) as f:
                return json.load(f)
        if code < 0:
            name = _signal_name(-code)
            err = InputError(f"{label}: its process was killed by {name}"
                             + (" (what the system's out-of-memory killer sends: try fewer "
                                "--columns or --objects)" if name == "SIGKILL" else ""))
            err.exit_code = 128 - code
            raise err
        try:
            with open(out + ".error") as f:
                why = f.read().strip()
        except OSError:
            why = ""
        why = why or said.last_line() or "(no message)"
        code = code or 1                # (exit 0 and no result: a failure all the same)
        err = InputError(f"{label}: its process failed (exit {code}): {why}"
                         + ("; --one-process runs it here, with its traceback"
                            if code == 1 else ""))
        err.exit_code = code
        raise err
    finally:
        shutil.rmtree(d, ignore_errors=True)


def _signal_name(sig: int) -> str:
    try:
        return signal.Signals(sig).name
    except ValueError:
        return f"signal {sig}"


def _die_with_parent(parent: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux's PR_SET_PDEATHSIG), and
    exit now if it already has."""
    try:
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)


def main(argv: list[str]) -> int:
    spec_path, out = argv
    with open(spec_path) as f:
        spec = json.load(f)
    _die_with_parent(spec["parent"])
    import drjit as dr
    if spec.get("threads"):
        dr.set_thread_count(spec["threads"])
    fn = getattr(importlib.import_module(spec["module"]), spec["function"])
    from rt_core.errors import USER_ERRORS

    def said(line: str) -> None:
        try:
            with open(out + ".error", "w") as f:
                f.write(line)
        except OSError:                 # (a full disk: the parent reads stderr instead)
            with contextlib.suppress(OSError):
                os.unlink(out + ".error")
            print(line, file=sys.stderr)
    try:
        if spec.get("warm"):
            fn(**spec["warm"])
        # (the process it ran in, and its Dr.Jit thread count)
        case = dict(fn(**spec["kwargs"]), pid=os.getpid(), drjit_threads=dr.thread_count())
    except USER_ERRORS as e:
        # (worded as the CLI words it in one process)
        if isinstance(e, OSError) and e.filename:
            said(f"{e.filename}: {(e.strerror or str(e)).lower()}")
        else:
            said(str(e).splitlines()[0] if str(e) else type(e).__name__)
        return getattr(e, "exit_code", 2)
    except Exception as e:              # a bug: its traceback on stderr, its last line here
        said(f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": "))
        raise
    try:
        with open(out, "w") as f:
            json.dump(case, f)
    except OSError as e:
        with contextlib.suppress(OSError):
            os.unlink(out)
        said(f"cannot write the case's result in {os.path.dirname(out)}: "
             f"{(e.strerror or str(e)).lower()}; free some space there or set TMPDIR to a "
             "folder that has some")
        return 2
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    sys.exit(main(sys.argv[1:]))
