"""Wall time of whole rtval commands in this process (--serial) and on a local Dask cluster
(--workers N), runs interleaved; prints median [min-max] per setting, the speed-up, and the
1-minute load average before each run (other processes on the machine skew the times).

    python benchmarks/parallel_speedup.py [--runs 3] [--workers 2] [--what validate stability]

validate: the default scenes (bundled and ../shared/course-scenes); stability: the default
full sweep (every parameter of every family, 64x48 rays).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {"validate": ["validate"], "stability": ["stability"]}


def run(what: str, where: list, out: str) -> float:
    extra = ["--json", os.path.join(out, "report.json")] if what == "stability" else []
    cmd = [sys.executable, "-m", "tools.cli", *COMMANDS[what], "-o", out, *extra, *where]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                       text=True)
    wall = time.perf_counter() - t0
    if r.returncode not in (0, 1):          # 1: a comparison failed; still a timed run
        sys.exit(f"{' '.join(cmd)} exited {r.returncode}: {r.stderr.strip()[-500:]}")
    return wall


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
    args = ap.parse_args()
    settings = {"serial": ["--serial"], f"dask {args.workers}": ["--workers", str(args.workers)]}
    for what in args.what:
        times = {k: [] for k in settings}
        loads = {k: [] for k in settings}
        with tempfile.TemporaryDirectory(prefix="rtval-bench-") as tmp:
            outs = {name: os.path.join(tmp, str(k)) for k, name in enumerate(settings)}
            for i in range(args.runs):
                order = list(settings) if i % 2 == 0 else list(reversed(settings))
                for name in order:
                    loads[name].append(os.getloadavg()[0])
                    times[name].append(run(what, settings[name], outs[name]))
                    print(f"{what} {name} run {i + 1}: {times[name][-1]:.1f} s "
                          f"(load {loads[name][-1]:.1f})", file=sys.stderr, flush=True)
            a, b = (_results(os.path.join(o, "report.json")) for o in outs.values())
            print(f"{what:10s} results (timing left out) identical: {a == b} "
                  f"({len(a)} rows)")
        med = {k: statistics.median(v) for k, v in times.items()}
        for name, v in times.items():
            print(f"{what:10s} {name:8s} {med[name]:7.1f} s [{min(v):.1f}-{max(v):.1f}]  "
                  f"load {min(loads[name]):.1f}-{max(loads[name]):.1f}")
        s, d = times["serial"], times[f"dask {args.workers}"]
        print(f"{what:10s} speed-up {med['serial'] / med[f'dask {args.workers}']:.2f}x "
              f"(range {min(s) / max(d):.2f}-{max(s) / min(d):.2f})")


if __name__ == "__main__":
    main()
