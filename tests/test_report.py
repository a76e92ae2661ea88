"""rtval report and rtval bench (tools/harness/report.py, tools/harness/bench.py): the pieces on
fixed inputs, and small end-to-end runs (no timed assertions: only that times are there)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tools.harness import bench, report


def test01_pareto_front():
    pts = [{"ns_per_ray": 1.0, "depth_p99_rel": 1e-6},     # front: fastest
           {"ns_per_ray": 2.0, "depth_p99_rel": 1e-6},     # dominated by 0
           {"ns_per_ray": 3.0, "depth_p99_rel": 1e-15},    # front: most accurate
           {"ns_per_ray": 3.0, "depth_p99_rel": 1e-14},    # dominated by 2
           {"ns_per_ray": 2.5, "depth_p99_rel": 1e-10}]    # front: in between
    assert report.pareto(pts, y="depth_p99_rel") == [0, 2, 4]


def test01b_wrong_pixels_keep_a_config_off_the_front():
    """A configuration that gets every pixel wrong has no same-object depth error (0); its
    error must still count the mismatches (it used to be marked best)."""
    rows = [{"config": c, "columns": 160, "rays": 100, "steady_ms": ms, "first_ms": 1,
             "compile_ms": 1, "sample": 100, "mask_mismatch": mm,
             "mask_mismatch_unflagged": mm, "depth_p99_rel": d, "depth_max_rel": d,
             "jit_peak_bytes": 0, "rss_peak_bytes": 0}
            for c, ms, mm, d in (("fast-wrong", 1.0, 100, 0.0), ("slow-right", 2.0, 0, 1e-7))]
    summ = report.summary(rows)
    assert [p["error"] for p in summ] == [1.0, 1e-7]
    assert report.pareto(summ) == [0, 1]       # neither dominates: fast but wrong, slow but right
    assert report.pareto([summ[0], dict(summ[1], steady_ms=0.5, ns_per_ray=0.1)]) == [1]


def test02_sample_index():
    assert np.array_equal(report.sample_index(50, 100, 1), np.arange(50))
    a = report.sample_index(10_000, 300, 7)
    assert len(a) == 300 and len(set(a.tolist())) == 300 and np.all(np.diff(a) > 0)
    assert np.array_equal(a, report.sample_index(10_000, 300, 7))


def test03_errors_against_the_oracle():
    from mitsuba_ref.oracle import DIAG_KEYS
    n = 6
    orc = {"hit.mask": np.array([1, 1, 1, 0, 0, 1.0]), "object.id": np.array([0, 1, 2, -1, -1, 3.]),
           "depth.Z": np.array([1.0, 2.0, 4.0, 0, 0, 8.0])}
    for k in DIAG_KEYS:
        orc[k] = np.full(n, np.inf)
    orc["edge_margin"][4] = 0.0                          # pixel 4's decision is at risk
    hit = np.array([1, 1, 0, 0, 1, 1], bool)
    oid = np.array([0, 1, -1, -1, 5, 3])
    depth = np.array([1.0, 2.0 * (1 + 1e-6), 0, 0, 3.0, 8.0 * (1 - 1e-3)])
    e = report.errors(hit, oid, depth, orc, "f32")
    assert e["mask_mismatch"] == 2 and e["mask_mismatch_unflagged"] == 1
    assert e["depth_pixels"] == 3
    assert e["depth_max_rel"] == pytest.approx(1e-3)


def test04_cli_defaults_match_the_library():
    from tools import cmd_bench
    assert tuple(cmd_bench.DEFAULT_OBJECTS) == bench.DEFAULT_OBJECTS
    assert tuple(cmd_bench.SCENES) == bench.SCENES


@pytest.mark.parametrize("kind", bench.SCENES)
def test05_bench_scenes(kind):
    s = bench.bench_scene(kind, 37)
    assert len(s.objects) == 37 + (2 if kind == "mixed" else 0)
    assert s.default_rows(1920) == 1080
    # everything behind the window: the screen clip decides nothing
    for o in s.objects:
        if o.kind == "sphere":
            assert o.center[2] + o.radius < 0
        elif o.kind == "fplane":
            assert max(c[2] for c in o.corners()) < 0
    assert bench.bench_scene(kind, 37) == s                 # deterministic


def test06_bench_case_small():
    r = bench.bench_case("mixed", 12, columns=64, reps=2, brute=True)
    t = r["tracers"]
    assert set(t) == set(bench.TRACERS) | set(bench.BRUTE)
    for name, row in t.items():
        assert row["median_ms"] > 0 and row["mrays_per_s"] > 0 and row["first_ms"] > 0
    # same rays: the variants of rt_core agree exactly, Mitsuba and f64 at a few edge rays
    assert t["rt_core-f32-nobins"]["differ_from_f32"] == 0
    assert t["rt_core-f32-unrolled"]["differ_from_f32"] == 0
    assert t["mitsuba"]["differ_from_f32"] <= 0.01 * r["rays"]
    assert t["rt_core-f64"]["differ_from_f32"] <= 0.01 * r["rays"]
    assert "ratio_f32_vs_mitsuba" in r and "ratio_f64_vs_mitsuba" in r
    # rt_core's own camera rays: float32's are the bench's rays (computed in the kernel
    # there), float64's its own, a few edge rays apart
    assert t["rt_core-f32-camera"]["differ_from_f32"] == 0
    assert t["rt_core-f64-camera"]["differ_from_f32"] <= 0.01 * r["rays"]
    assert r["f64_vs_f32_camera"] == round(t["rt_core-f32-camera"]["median_ms"] /
                                           t["rt_core-f64-camera"]["median_ms"], 3)
    g = bench.growth([r])
    assert "mixed" in g


def test07_report_end_to_end(tmp_path):
    from rt_core.parser import parse_scene
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    scenes = [parse_scene(os.path.join(root, "scenes", "mixed.txt"))]
    res = report.run_report(scenes, report.Settings(columns=(24, 40), sample=200, reps=1))
    assert len(res["rows"]) == 2 * len(report.CONFIGS)
    for r in res["rows"]:
        assert r["steady_ms"] > 0 and r["first_ms"] > 0
        assert r["sample"] == min(200, r["rays"])
        assert r["scene_sha256"] == scenes[0].sha256 and len(r["scene_sha256"]) == 64
    rt = [r for r in res["rows"] if r["tracer"].startswith("rt_core")]
    assert all(r["mask_mismatch_unflagged"] == 0 for r in rt)
    assert all(r["depth_max_rel"] < 1e-5 for r in rt if r["precision"] == "f32")
    assert all(r["depth_max_rel"] < 1e-13 for r in rt if r["precision"] == "f64")
    md, js, png = report.write_report(res, str(tmp_path))
    data = json.loads(open(js).read())
    assert data["meta"]["sample"] == 200 and data["pareto"]
    assert "oracle" in open(md).read() and os.path.getsize(png) > 1000


def test08_the_three_files_together_or_none(tmp_path, monkeypatch):
    """A full disk left the PNG and a new directory when the JSON could not be written (a
    review): the three files are renamed into place together, and a directory the write
    made is removed when it fails."""
    from rt_core.outputs import WriteError
    from rt_core.parser import parse_scene
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = report.run_report([parse_scene(os.path.join(root, "scenes", "sphere.txt"))],
                            report.Settings(columns=(16,), sample=20, reps=1))

    def full(path, data, indent=1):
        raise WriteError(path, "no space left on device")
    monkeypatch.setattr("rt_core.outputs.write_json", full)
    out = tmp_path / "new" / "rep"
    with pytest.raises(WriteError):
        report.write_report(res, str(out))
    assert list(tmp_path.iterdir()) == []
    out.mkdir(parents=True)                         # an earlier report's directory stays
    (out / "report.md").write_text("old")
    with pytest.raises(WriteError):
        report.write_report(res, str(out))
    assert sorted(p.name for p in out.iterdir()) == ["report.md"]
    assert (out / "report.md").read_text() == "old"
