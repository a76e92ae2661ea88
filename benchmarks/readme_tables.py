"""The README's speed tables from `rtval bench --json` / `-o` files: every cell the median of
the runs and [their range], so that the README carries measured numbers, never copied ones.

    python benchmarks/readme_tables.py run1.json run2.json run3.json

Primary-ray runs (`rtval bench`) give the ratio table (rt_core f32 and f64 against Mitsuba,
and f64 with exact decisions against without), the f64/f32 speed table, and the f64/f32 speed
table on rt_core's own camera rays (`rtval render`'s: tracers rt_core-f32-camera and
rt_core-f64-camera; runs from before they existed leave its cells empty); shaded runs
(`rtval bench --shaded`) the shaded ratio table.  Runs of both modes can be given together.
"""
from __future__ import annotations

import json
import statistics
import sys

SCENES = ("fplanes", "spheres", "mixed")
NAMES = {"fplanes": "finite planes", "spheres": "spheres", "mixed": "mixed"}


def _cell(values, fmt="{:.2f}", unit="×") -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    med = statistics.median(values)
    if len(values) == 1:
        return fmt.format(med) + unit
    return f"{fmt.format(med)}{unit} [{fmt.format(min(values))}–{fmt.format(max(values))}]"


def _by_case(runs):
    """{(scene, objects): [case of each run]}."""
    out: dict = {}
    for run in runs:
        for c in run["cases"]:
            out.setdefault((c["scene"], c["objects"]), []).append(c)
    return out


def _ratio(c, tracer):
    r = c["tracers"].get(tracer, {})
    return r.get("ratio_vs_mitsuba")


def _layout(runs):
    """(cases by (scene, objects), the object counts, the scene kinds present)."""
    cases = _by_case(runs)
    return cases, sorted({n for _, n in cases}), [s for s in SCENES
                                                   if any(k[0] == s for k in cases)]


def _table(head, rows) -> list:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + \
        ["| " + " | ".join(r) + " |" for r in rows]


def ratio_table(runs, extra=None) -> list:
    """Per object count and scene kind, rt_core f32's and f64's ratio to Mitsuba; ``extra``:
    (heading, fn(cases of one count, scene kinds) -> cell) of a last column."""
    cases, counts, scenes = _layout(runs)
    head = ["objects"] + [f"{NAMES[s]}, {p}" for s in scenes for p in ("f32", "f64")]
    rows = []
    for n in counts:
        row = [str(n)]
        for s in scenes:
            cs = cases.get((s, n), [])
            row += [_cell([_ratio(c, f"rt_core-{p}") for c in cs]) for p in ("f32", "f64")]
        if extra:
            row.append(extra[1]({s: cases.get((s, n), []) for s in scenes}))
        rows.append(row)
    return _table(head + ([extra[0]] if extra else []), rows)


def _f64_over_f32(c):
    a, b = c["tracers"].get("rt_core-f32"), c["tracers"].get("rt_core-f64")
    return a["median_ms"] / b["median_ms"] if a and b else None


def primary_tables(runs) -> str:
    cases, counts, scenes = _layout(runs)
    exact = ("f64 exact / plain (" + "; ".join(scenes) + ")",
             lambda by: "; ".join(_cell([c.get("f64_exact_vs_plain") for c in by[s]], unit="")
                                  for s in scenes))
    speed = _table(["objects", "f64 / f32 speed: " + NAMES[scenes[0]]] +
                   [NAMES[s] for s in scenes[1:]],
                   [[str(n)] + [_cell([_f64_over_f32(c) for c in cases.get((s, n), [])], unit="")
                                for s in scenes] for n in counts])
    camera = _table(["objects", "f64 / f32 speed, camera rays: " + NAMES[scenes[0]]] +
                    [NAMES[s] for s in scenes[1:]],
                    [[str(n)] + [_cell([c.get("f64_vs_f32_camera")
                                        for c in cases.get((s, n), [])], unit="")
                                 for s in scenes] for n in counts])
    return "\n".join(ratio_table(runs, exact) + [""] + speed + [""] + camera)


def shaded_table(runs) -> str:
    return "\n".join(ratio_table(runs))


def _kind(run) -> str | None:
    """'shaded', 'primary', or None for JSON that is not an `rtval bench` run of either."""
    if not isinstance(run, dict) or not isinstance(run.get("cases"), list):
        return None
    if run.get("mode") == "shaded":
        return "shaded"
    return "primary" if "growth" in run else None


def main(paths) -> int:
    if not paths:
        print("usage: python benchmarks/readme_tables.py RUN.json ...", file=sys.stderr)
        return 2
    runs = []
    for p in paths:
        try:
            with open(p) as f:
                run = json.load(f)
        except (OSError, ValueError) as e:
            print(f"readme_tables: {p}: cannot read a JSON run ({e}); give the -o file of "
                  "`rtval bench`", file=sys.stderr)
            return 2
        if _kind(run) is None:
            print(f"readme_tables: {p}: not an `rtval bench` run (primary or --shaded); "
                  "give the -o file of `rtval bench`", file=sys.stderr)
            return 2
        runs.append(run)
    primary = [r for r in runs if _kind(r) == "primary"]
    shaded = [r for r in runs if _kind(r) == "shaded"]
    groups = (("primary rays", primary, primary_tables),
              ("shaded images", shaded, shaded_table))
    for label, group, _ in groups:
        # (runs from before the JSON said where its cases ran had them all in one process)
        ways = {r["meta"].get("cases_in", "one process") for r in group}
        if len(ways) > 1:
            print(f"readme_tables: the {label} runs ran their cases differently "
                  f"({'; '.join(sorted(ways))}); give runs made one way (`rtval bench` "
                  "runs each case in a process of its own, `--one-process` all in one)",
                  file=sys.stderr)
            return 2
    for label, group, fn in groups:
        if group:
            commits = sorted({r["meta"].get("commit", "?") for r in group})
            where = group[0]["meta"].get("cases_in", "one process")
            print(f"<!-- {label}: {len(group)} runs, commit {', '.join(commits)}, cases in "
                  f"{where} -->")
            print(fn(group))
            print()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
