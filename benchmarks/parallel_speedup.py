"""Wall time of whole rtval commands in this process (--serial) and on a local Dask cluster
(--workers N), runs interleaved; prints median [min-max] per setting, the speed-up, the CPU
seconds the run used (rtval, its workers and the fork server together; sampled every 0.2 s,
so a little low), and the 1-minute load average before each run (other processes on the
machine skew the times; --quiet L waits, up to --max-wait seconds, for the load to fall to
L before each run).  Checks that the serial and the Dask runs' results are identical,
timing left out.

    python benchmarks/parallel_speedup.py [--runs 3] [--workers 2] [--what validate stability]

validate: the default scenes (bundled and ../shared/course-scenes); stability: the default
full sweep (every parameter of every family, 64x48 rays); stability-quick: --quick.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {"validate": ["validate"], "stability": ["stability"],
            "stability-quick": ["stability", "--quick"]}


def run(what: str, where: list, out: str) -> tuple[float, float]:
    """(wall seconds, CPU seconds of rtval and every process it started: the Dask workers
    are reaped by the fork server, so their CPU is sampled from /proc while they run)."""
    import psutil
    extra = ["--json", os.path.join(out, "report.json")] if what == "stability" else []
    cmd = [sys.executable, "-m", "tools.cli", *COMMANDS[what], "-o", out, *extra, *where]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True)
    cpu = {}
    root = psutil.Process(p.pid)
    while p.poll() is None:
        try:
            for q in [root, *root.children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    t = q.cpu_times()
                    cpu[q.pid] = t.user + t.system
        except psutil.Error:
            pass
        time.sleep(0.2)
    err = p.stderr.read()
    wall = time.perf_counter() - t0
    if p.returncode not in (0, 1):          # 1: a comparison failed; still a timed run
        sys.exit(f"{' '.join(cmd)} exited {p.returncode}: {err.strip()[-500:]}")
    return wall, sum(cpu.values())


def wait_quiet(limit: float | None, max_wait: float) -> float:
    """Wait until the 1-minute load average is at most ``limit`` (or max_wait passed)."""
    t0 = time.monotonic()
    while limit is not None and os.getloadavg()[0] > limit and \
            time.monotonic() - t0 < max_wait:
        time.sleep(5)
    return os.getloadavg()[0]


def _results(path: str) -> list:
    """The rows of a report.json (validate) or the cases of stability's JSON, without their
    timing fields, as JSON text (NaN-safe comparison)."""
    import json
    data = json.loads(Path(path).read_text())
    rows = data.get("results", data.get("cases"))
    drop = {"rt_core_ms", "mitsuba_ms", "seconds"}
    return [json.dumps({k: v for k, v in r.items() if k not in drop}, sort_keys=True)
            for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--what", nargs="+", default=list(COMMANDS), choices=list(COMMANDS))
    ap.add_argument("--quiet", type=float, default=None, metavar="LOAD")
    ap.add_argument("--max-wait", type=float, default=600)
    args = ap.parse_args()
    settings = {"serial": ["--serial"], f"dask {args.workers}": ["--workers", str(args.workers)]}
    for what in args.what:
        times = {k: [] for k in settings}
        cpus = {k: [] for k in settings}
        loads = {k: [] for k in settings}
        with tempfile.TemporaryDirectory(prefix="rtval-bench-") as tmp:
            outs = {name: os.path.join(tmp, str(k)) for k, name in enumerate(settings)}
            for i in range(args.runs):
                order = list(settings) if i % 2 == 0 else list(reversed(settings))
                for name in order:
                    loads[name].append(wait_quiet(args.quiet, args.max_wait))
                    wall, cpu = run(what, settings[name], outs[name])
                    times[name].append(wall)
                    cpus[name].append(cpu)
                    print(f"{what} {name} run {i + 1}: {wall:.1f} s, CPU {cpu:.1f} s "
                          f"(load {loads[name][-1]:.1f})", file=sys.stderr, flush=True)
            a, b = (_results(os.path.join(o, "report.json")) for o in outs.values())
            print(f"{what:10s} results (timing left out) identical: {a == b} "
                  f"({len(a)} rows)")
        med = {k: statistics.median(v) for k, v in times.items()}
        for name, v in times.items():
            print(f"{what:10s} {name:8s} {med[name]:7.1f} s [{min(v):.1f}-{max(v):.1f}]  "
                  f"CPU {statistics.median(cpus[name]):.1f} s  "
                  f"load {min(loads[name]):.1f}-{max(loads[name]):.1f}")
        s, d = times["serial"], times[f"dask {args.workers}"]
        print(f"{what:10s} speed-up {med['serial'] / med[f'dask {args.workers}']:.2f}x "
              f"(range {min(s) / max(d):.2f}-{max(s) / min(d):.2f})")


if __name__ == "__main__":
    main()
