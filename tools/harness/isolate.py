"""One benchmark case in a Python process of its own (``rtval bench``'s default, every mode
but ``--command``, which starts a process per run anyway).

In one process a case's times depend on the cases before it: Dr.Jit keeps what earlier cases
loaded (their kernels, tables that never shrink), and the later cases trace and run slower.
Measured (primary rays, 1920 columns, same commit): spheres 16's rt_core float32 took 3.80 ms
after the finite-plane cases, 3.40 ms on its own, while Mitsuba's 7.78 and 7.98 ms stayed
within its spread (docs/speed.md, "Each case in a process of its own").

The child first runs a small case of the same function (``warm``): what the first case of a
run in one process pays once (Dr.Jit's LLVM back end, Mitsuba's variant and plugins) is then
paid before the measured case, not inside its first call.  It writes the case's JSON to a
file in a temporary folder, which the parent reads and removes.  A child that fails ends the
run with one line: its error's, which it writes to a file beside the JSON (stderr's last line
where it wrote none: a crash).  A signal that ends the parent ends the child too
(``subprocess.run`` kills it on the way out).

    python -m tools.harness.isolate SPEC.json OUT.json   (the child; SPEC from ``run_case``)
"""
from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run_case(label: str, module: str, function: str, kwargs: dict, warm: dict | None = None,
             threads: int | None = None) -> dict:
    """``module.function(**kwargs)`` (a JSON-able dict) in a new Python process, after
    ``module.function(**warm)`` there; ``threads``: Dr.Jit's worker threads there."""
    from rt_core.usererror import InputError
    spec = {"module": module, "function": function, "kwargs": kwargs, "warm": warm,
            "threads": threads}
    with tempfile.TemporaryDirectory(prefix="rtval-case-") as d:
        spec_path, out = os.path.join(d, "spec.json"), os.path.join(d, "case.json")
        with open(spec_path, "w") as f:
            json.dump(spec, f)
        r = subprocess.run([sys.executable, "-m", "tools.harness.isolate", spec_path, out],
                           cwd=REPO, capture_output=True, text=True)
        if r.returncode != 0 or not os.path.exists(out):
            # its error's line, as the child wrote it (what Dr.Jit or nanobind print at
            # exit may follow it on stderr), else stderr's last line (a crash)
            try:
                with open(out + ".error") as f:
                    last = f.read().strip()
            except OSError:
                last = (r.stderr.strip().splitlines() or ["(no message)"])[-1]
            err = InputError(f"{label}: its process failed (exit {r.returncode}): {last}")
            err.exit_code = r.returncode if r.returncode in (1, 2) else 1
            raise err
        with open(out) as f:
            return json.load(f)


def main(argv: list[str]) -> int:
    spec_path, out = argv
    with open(spec_path) as f:
        spec = json.load(f)
    if spec.get("threads"):
        import drjit as dr
        dr.set_thread_count(spec["threads"])
    fn = getattr(importlib.import_module(spec["module"]), spec["function"])
    from rt_core.errors import USER_ERRORS

    def said(line: str) -> None:
        with open(out + ".error", "w") as f:
            f.write(line)
    try:
        if spec.get("warm"):
            fn(**spec["warm"])
        case = dict(fn(**spec["kwargs"]), pid=os.getpid())   # (the process it ran in)
    except USER_ERRORS as e:
        said(str(e).splitlines()[0] if str(e) else type(e).__name__)
        print(f"rtval bench: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
              file=sys.stderr)
        return getattr(e, "exit_code", 2)
    except Exception as e:              # a bug: its traceback on stderr, its last line here
        said(f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": "))
        raise
    with open(out, "w") as f:
        json.dump(case, f)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    sys.exit(main(sys.argv[1:]))
