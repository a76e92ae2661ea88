"""rtval bench --command and --shaded: smoke runs (CI); the figures themselves come from real
runs."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test01_command_bench_splits_a_render_into_phases(tmp_path):
    out = tmp_path / "c.json"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--command",
                        "--command-columns", "48", "--runs", "1", "-o", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(out.read_text())
    assert res["mode"] == "command" and {c["outputs"] for c in res["cases"]} == \
        {"geometry", "shaded", "course"}
    for c in res["cases"]:
        p = c["phases"]
        assert c["columns"] == 48 and c["runs"] == 1
        parts = sum(p[k]["median"] for k in ("import", "parse", "kernel", "write"))
        assert abs(parts - p["wall"]["median"]) < 1e-6 and all(
            p[k]["median"] > 0 for k in ("import", "kernel", "write"))
        assert c["largest"] in ("import", "parse", "kernel", "write")
    assert "largest" in r.stdout and "kernel" in r.stdout


def test02_shaded_bench_smoke(tmp_path):
    """rtval bench --shaded, tiny: every field there, and both sides cast the same rays (the
    same reflection rays; shadow rays within 2%: rt_core's plane kinds are infinite where
    Mitsuba's stand-ins end, and float32 edges)."""
    out = tmp_path / "s.json"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--shaded", "--objects", "1",
                        "4", "--columns", "32", "--reps", "1", "--scenes", "mixed", "--tracers",
                        "rt_core-f32", "mitsuba", "-o", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(out.read_text())
    assert res["mode"] == "shaded" and res["meta"]["lights"] == 4
    assert [c["objects"] for c in res["cases"]] == [1, 4]
    for c in res["cases"]:
        assert c["pixels"] == 32 * 18 and set(c["tracers"]) == {"rt_core-f32", "mitsuba"}
        ours, mi = c["tracers"]["rt_core-f32"], c["tracers"]["mitsuba"]
        for r_ in (ours, mi):
            assert r_["median_ms"] > 0 and r_["min_ms"] <= r_["median_ms"]
            assert r_["shadow_rays"] > 0 and r_["reflection_rays"] > 0
        assert ours["ratio_vs_mitsuba"] > 0 and "ratio_f32_vs_mitsuba" in c
        assert ours["reflection_rays"] == mi["reflection_rays"]
        assert abs(ours["shadow_rays"] - mi["shadow_rays"]) <= 0.02 * mi["shadow_rays"]
        assert abs(ours["shadow_blocked"] - mi["shadow_blocked"]) <= \
            0.02 * mi["shadow_blocked"] + 2
        assert ours["pixels_differ_from_mitsuba"] <= 0.02 * c["pixels"]
    assert "vs Mitsuba" in r.stdout and "shadow rays" in r.stdout


def test03_shaded_bench_usage_errors():
    for extra in (["--command"], ["--brute"]):
        r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--shaded", *extra],
                           cwd=REPO, capture_output=True, text=True, timeout=60)
        assert r.returncode == 64 and "do not go together" in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1


def test04_shaded_defaults_agree():
    # tools/cmd_bench.py writes them out (it must not import Dr.Jit before parsing)
    from tools import cmd_bench
    from tools.harness import bench_shaded
    assert tuple(cmd_bench.SHADED_OBJECTS) == bench_shaded.SHADED_OBJECTS
    assert cmd_bench.DEFAULT_LIGHTS == bench_shaded.DEFAULT_LIGHTS
    assert tuple(cmd_bench.SHADED_TRACERS) == bench_shaded.TRACERS
