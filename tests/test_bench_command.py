"""rtval bench --command and --shaded: smoke runs (CI); the figures themselves come from real
runs."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

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
        parts = sum(p[k]["median"] for k in ("import", "parse", "kernel", "write", "exit"))
        assert abs(parts - p["wall"]["median"]) < 1e-6 and all(
            p[k]["median"] > 0 for k in ("import", "kernel", "write", "exit"))
        assert c["largest"] in ("import", "parse", "kernel", "write", "exit")
    assert "largest" in r.stdout and "kernel" in r.stdout
    assert res["machine"]["backend"] == "llvm"
    # its provenance, as every output's (it had the machine alone: a review)
    import hashlib
    assert res["scene_sha256"] == hashlib.sha256((REPO / res["scene"]).read_bytes()).hexdigest()
    assert res["rtval"] and res["drjit"] and "python" in res
    assert "warm-up" in res["bytecode"]


def test01b_timed_renders_read_compiled_bytecode(tmp_path, monkeypatch):
    """Each timed render reads the bytecode its warm-up run wrote, as an installed rtval
    does: with PYTHONDONTWRITEBYTECODE (set on this project's machines) every run compiled
    every module again, 0.2-0.4 s of its import phase."""
    from tools.harness.bench import command_env
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    env = command_env(str(tmp_path))
    assert "PYTHONDONTWRITEBYTECODE" not in env and env["PATH"] == os.environ["PATH"]
    code = "import tools.harness.flip"
    for _ in range(2):
        subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, check=True)
    cached = list((tmp_path / "pycache").rglob("flip*.pyc"))
    assert len(cached) == 1, cached


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
    assert res["meta"]["backend"] == "llvm" and {c["backend"] for c in res["cases"]} == {"llvm"}
    assert [c["objects"] for c in res["cases"]] == [1, 4]
    for c in res["cases"]:
        assert c["pixels"] == 32 * 18 and set(c["tracers"]) == {"rt_core-f32", "mitsuba"}
        ours, mi = c["tracers"]["rt_core-f32"], c["tracers"]["mitsuba"]
        for r_ in (ours, mi):
            assert r_["median_ms"] > 0 and r_["min_ms"] <= r_["median_ms"]
            assert r_["first_ms"] > 0 and r_["second_ms"] > 0
            assert r_["shadow_rays"] > 0 and r_["reflection_rays"] > 0
        assert ours["ratio_vs_mitsuba"] > 0 and "ratio_f32_vs_mitsuba" in c
        assert ours["timed_image_is_counted"] is True
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


@pytest.mark.parametrize("mode", [[], ["--shaded"]], ids=["primary", "shaded"])
def test03b_bench_too_large_is_one_line_and_its_estimate_bounds_the_peak(mode, tmp_path):
    """rtval bench refuses an image too large for the machine in one line (exit 2, the
    largest --columns that fits, nothing written) before tracing; and its estimate
    (memory.bench_bytes) bounds the real peak RSS of a run that fits."""
    from rt_core.memory import bench_bytes
    out = tmp_path / "b.json"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", *mode, "--columns",
                        "200000", "--objects", "1", "-o", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "needs ~" in lines[0] and "use --columns <= " in lines[0] and not out.exists()
    # (large enough that the per-pixel figure, not the base, counts; 256 objects, whose peak
    # is above 1 object's: 1.29 against 1.07 GB shaded)
    columns = 1280
    code = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
            "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    r = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "tools.cli",
                        "bench", *mode, "--columns", str(columns), "--objects", "256",
                        "--scenes", "mixed", "--reps", "1", "--keep-cache", "-o", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    rc, peak = map(int, r.stdout.split()[-2:])
    assert rc == 0, r.stderr[-2000:]
    assert peak * 1024 < bench_bytes(columns * (columns * 9 // 16), bool(mode))


def test04_shaded_defaults_agree():
    # tools/cmd_bench.py writes them out (it must not import Dr.Jit before parsing)
    from tools import cmd_bench
    from tools.harness import bench_shaded
    assert tuple(cmd_bench.SHADED_OBJECTS) == bench_shaded.SHADED_OBJECTS
    assert cmd_bench.DEFAULT_LIGHTS == bench_shaded.DEFAULT_LIGHTS
    assert tuple(cmd_bench.SHADED_TRACERS) == bench_shaded.TRACERS


def _has_cuda() -> bool:
    import drjit as dr
    return dr.has_backend(dr.JitBackend.CUDA)


@pytest.mark.parametrize("mode", [["--objects", "1", "--columns", "32"],
                                  ["--shaded", "--objects", "1", "--columns", "32"],
                                  ["--command", "--command-columns", "32"]],
                         ids=["primary", "shaded", "command"])
def test05_cuda_backend_without_a_gpu_says_so(mode, tmp_path):
    """rtval bench --backend cuda where Dr.Jit finds no CUDA device: one line that says so and
    what to do, exit 2, nothing written (every mode)."""
    if _has_cuda():
        pytest.skip("this machine has CUDA: test06 runs the benchmark there")
    out = tmp_path / "b.json"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--backend", "cuda", *mode,
                        "-o", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and not out.exists()
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "CUDA" in lines[0] and "--backend llvm" in lines[0], r.stderr


@pytest.mark.skipif(not _has_cuda(), reason="no CUDA device here")
def test06_cuda_backend_bench_smoke(tmp_path):
    """On a GPU: the primary and the shaded modes run on Dr.Jit's CUDA backend against
    Mitsuba's cuda_ad_rgb, and both sides find the same objects."""
    for mode in ([], ["--shaded", "--tracers", "rt_core-f32", "mitsuba"]):
        out = tmp_path / "b.json"
        r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--backend", "cuda",
                            *mode, "--objects", "1", "16", "--columns", "64", "--reps", "1",
                            "--scenes", "mixed", "-o", str(out)],
                           cwd=REPO, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        res = json.loads(out.read_text())
        assert res["meta"]["backend"] == "cuda" and res["meta"]["gpu"]
        assert res["meta"]["cases_in"].startswith("a process each")
        for c in res["cases"]:
            assert c["backend"] == "cuda" and c["ratio_f32_vs_mitsuba"] > 0 and c["pid"]
            if not mode:
                assert c["tracers"]["mitsuba"]["differ_from_f32"] <= 0.01 * c["rays"]
            else:
                assert c["tracers"]["rt_core-f32"]["pixels_differ_from_mitsuba"] <= \
                    0.02 * c["pixels"]


class _Stop(Exception):
    pass


def test07_every_mode_passes_the_backend_on(monkeypatch):
    """(Without a GPU) each mode asks for the chosen backend's types, Mitsuba variant and
    `rtval render --backend`: the calls are recorded, and stopped at the first."""
    from rt_core import backend
    from mitsuba_ref import convert
    from tools.harness import bench, bench_shaded
    seen = []

    def types(precision="f32", backend_name="llvm"):
        seen.append(("types", backend_name))
        raise _Stop

    def mitsuba(variant=convert.VARIANT):
        seen.append(("mitsuba", variant))
        raise _Stop

    def run(args, **kw):
        seen.append(("render", args[args.index("--backend") + 1]))
        raise _Stop
    monkeypatch.setattr(backend, "types", types)
    monkeypatch.setattr(convert, "mitsuba", mitsuba)
    monkeypatch.setattr("subprocess.run", run)
    for call in (lambda: bench.bench_case("mixed", 1, 32, 1, backend_name="cuda"),
                 lambda: bench_shaded.shaded_case("mixed", 1, 32, 1, backend_name="cuda"),
                 lambda: bench.command_bench([32], 1, backend_name="cuda")):
        with pytest.raises(_Stop):
            call()
    assert seen == [("types", "cuda")] * 2 + [("render", "cuda")]
    seen.clear()
    d32 = object()
    for call in (lambda: bench.mitsuba_tracer(bench.bench_scene("mixed", 1), d32, 32, "cuda"),
                 lambda: bench_shaded.mitsuba_side(bench.bench_scene("mixed", 1), d32, 32,
                                                   backend_name="cuda")):
        with pytest.raises(_Stop):
            call()
    assert seen == [("mitsuba", "cuda_ad_rgb")] * 2


def test08_readme_tables_from_bench_runs(tmp_path):
    """benchmarks/readme_tables.py: the README's tables from two tiny `rtval bench -o` runs,
    every cell the runs' median and [range] of the ratios the runs recorded."""
    paths = []
    for k in range(2):
        out = tmp_path / f"b{k}.json"
        r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--objects", "1",
                            "--columns", "32", "--reps", "1", "--scenes", "spheres",
                            "--keep-cache", "-o", str(out)],
                           cwd=REPO, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        paths.append(out)
    r = subprocess.run([sys.executable, "benchmarks/readme_tables.py", *map(str, paths)],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    ratios = sorted(json.loads(p.read_text())["cases"][0]["tracers"]["rt_core-f32"]
                    ["ratio_vs_mitsuba"] for p in paths)
    row = next(l for l in r.stdout.splitlines() if l.startswith("| 1 |"))
    med = (ratios[0] + ratios[1]) / 2
    assert row.split(" | ")[1] == f"{med:.2f}× [{ratios[0]:.2f}–{ratios[1]:.2f}]", row
    assert "2 runs" in r.stdout and "f64 / f32 speed" in r.stdout
    assert "cases in a process each (after a warm-up case there) -->" in r.stdout
    cams = sorted(json.loads(p.read_text())["cases"][0]["f64_vs_f32_camera"] for p in paths)
    head = r.stdout.index("f64 / f32 speed, camera rays")
    row = next(l for l in r.stdout[head:].splitlines() if l.startswith("| 1 |"))
    assert row == f"| 1 | {(cams[0] + cams[1]) / 2:.2f} [{cams[0]:.2f}–{cams[1]:.2f}] |", row
    # runs whose cases ran differently are not one table's: one line, exit 2
    one = json.loads(paths[1].read_text())
    one["meta"]["cases_in"] = "one process"
    paths[1].write_text(json.dumps(one))
    r = subprocess.run([sys.executable, "benchmarks/readme_tables.py", *map(str, paths)],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stdout == "" and len(r.stderr.strip().splitlines()) == 1
    assert "ran their cases differently" in r.stderr, r.stderr


def test08b_readme_tables_refuse_what_is_not_a_run(tmp_path):
    """A file that is not an `rtval bench` run (another JSON, a cut file, a missing one) is
    one line naming it, exit 2: never a table silently short of a run."""
    other = tmp_path / "report.json"
    other.write_text(json.dumps({"rows": []}))
    cut = tmp_path / "cut.json"
    cut.write_text('{"cases": [')
    for bad in (other, cut, tmp_path / "missing.json"):
        r = subprocess.run([sys.executable, "benchmarks/readme_tables.py", str(bad)],
                           cwd=REPO, capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and r.stdout == "", (bad, r.stdout)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and str(bad) in lines[0] and "Traceback" not in r.stderr


def test08c_validate_split_clocks_each_function(tmp_path):
    """benchmarks/validate_split.py: a validate of two scenes (rays and shaded, float32; the
    torus's exact comparison) in its process, each clocked function with its phase and
    calls: the geometry traces (the exact comparison's too, which validate charges to
    rt_core), Mitsuba's rays, the classifier, the shaded renders, Mitsuba's course images,
    the exact oracle; the report where ``--output=`` puts it."""
    r = subprocess.run([sys.executable, "benchmarks/validate_split.py", "scenes/mixed.txt",
                        "scenes/torus.txt", "--precision", "f32", "--mode", "rays",
                        "--shaded-columns", "16", "--exact-columns", "8",
                        "--oracle-columns", "0", f"--output={tmp_path}"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = {ln.split()[1]: ln.split() for ln in r.stdout.splitlines()
            if ln.split()[:1] in (["rt_core"], ["mitsuba"], ["classify"], ["oracles"])}
    want = {"rt_core.render.trace_geometry": ("rt_core", 3),
            "rt_core.render.render_image": ("rt_core", 2),
            "mitsuba_ref.reference.trace_rays": ("mitsuba", 2),
            "tools.harness.shaded.mitsuba_course_image": ("mitsuba", 2),
            "mitsuba_ref.explain.classify": ("classify", 2),
            "tools.harness.shaded.classify_shaded": ("classify", 2),
            "mitsuba_ref.exact.trace_exact": ("oracles", 1)}
    for name, (phase, calls) in want.items():
        assert name in rows and rows[name][0] == phase and rows[name][3] == str(calls), \
            (name, rows.get(name), r.stdout[-2000:])
    assert (tmp_path / "report.json").exists()


def test08d_validate_split_passes_on_validates_refusal(tmp_path):
    """benchmarks/validate_split.py on input validate refuses (a missing scene, an unknown
    option): validate's one line and exit code, no table, and the folder it made for the
    report removed."""
    for args, code in ((["/nonexistent/scene.txt"], 2), (["--bogus"], 64)):
        r = subprocess.run([sys.executable, "benchmarks/validate_split.py", *args], cwd=REPO,
                           capture_output=True, text=True, timeout=120,
                           env={**os.environ, "TMPDIR": str(tmp_path)})
        assert r.returncode == code and r.stdout == "", (args, r.stdout)
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
        assert not list(tmp_path.iterdir()), list(tmp_path.iterdir())


def test09_the_scene_helpers_keep_the_benchmarks_variant(monkeypatch):
    """(Without a GPU: scalar_rgb stands in for cuda_ad_rgb) once a benchmark has set its
    backend's variant, building the scene (convert.scene_dict) keeps it: a CUDA benchmark's
    Mitsuba scene is a CUDA one; convert.mitsuba() itself means rtval's variant."""
    from mitsuba_ref import convert
    from tools.harness.bench import bench_scene
    monkeypatch.setitem(convert.VARIANTS, "cuda", "scalar_rgb")
    try:
        mi = convert.mitsuba(convert.VARIANTS["cuda"])
        convert.scene_dict(bench_scene("mixed", 1), 32, None, integrator=False, clip=False)
        assert mi.variant() == "scalar_rgb"
        # and the references after it (validate, compare, render --mitsuba in the same
        # process) are back in rtval's own variant, not the benchmark's
        assert convert.mitsuba().variant() == convert.VARIANT
    finally:
        monkeypatch.undo()
        convert.mitsuba(convert.VARIANT)


@pytest.mark.parametrize("args, said", [
    (("--tracers", "mitsuba", "--runs", "5", "--scene", "/nonexistent.txt"),
     "--scene, --runs, --tracers not used by the default mode"),
    (("--command", "--threads", "1", "--objects", "4", "--reps", "7", "--one-process"),
     "--objects, --reps, --threads, --one-process not used by --command"),
    (("--shaded", "--runs", "2"), "--runs not used by --shaded")],
    ids=["default", "command", "shaded"])
def test09_options_of_another_mode_are_usage_errors(args, said):
    """Options of another mode were accepted and ignored, exit 0: --tracers mitsuba timed all
    four tracers, a missing --scene was never read (a review).  Now exit 64, naming them."""
    r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", *args], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    err = r.stderr.strip()
    assert r.returncode == 64 and len(err.splitlines()) == 1 and said in err, err


# --- each case in a process of its own (tools/harness/isolate.py) ----------------------------

def test10_each_case_runs_in_a_process_of_its_own(tmp_path, monkeypatch):
    """rtval bench's default, both modes: every case in a new process, with the same answers
    as in one process (``isolated=False``, --one-process), and its folder removed."""
    import tempfile
    from tools.harness import bench, bench_shaded
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    iso = bench.run_bench([1, 4], ["spheres"], columns=32, reps=1)
    one = bench.run_bench([1, 4], ["spheres"], columns=32, reps=1, isolated=False)
    pids = [c["pid"] for c in iso["cases"]]
    assert len(set(pids)) == 2 and os.getpid() not in pids
    assert all("pid" not in c for c in one["cases"])
    assert (iso["meta"]["cases_in"], one["meta"]["cases_in"]) == \
        (bench.PROCESS[True], bench.PROCESS[False])
    for a, b in zip(iso["cases"], one["cases"]):
        assert (a["scene"], a["objects"], a["rays"]) == (b["scene"], b["objects"], b["rays"])
        assert set(a["tracers"]) == set(b["tracers"])
        assert {k: v.get("differ_from_f32") for k, v in a["tracers"].items()} == \
            {k: v.get("differ_from_f32") for k, v in b["tracers"].items()}
    sh = bench_shaded.run_shaded([1], ["spheres"], columns=32, reps=1,
                                 tracers=["rt_core-f32", "mitsuba"], threads=1)
    assert sh["cases"][0]["pid"] not in (os.getpid(), *pids)
    assert sh["cases"][0]["drjit_threads"] == 1       # (--threads reaches the case's process)
    assert sh["meta"]["cases_in"] == bench.PROCESS[True]
    assert sh["cases"][0]["tracers"]["rt_core-f32"]["pixels_differ_from_mitsuba"] <= 0.02 * 32 * 18
    assert os.listdir(tmp_path) == []


def test10a_the_warm_up_makes_what_every_case_shares_and_none_of_the_case(tmp_path,
                                                                          monkeypatch):
    """The case's process warms up on another scene kind first: with an empty kernel cache,
    the measured case's first call still compiles rt_core's kernels of that case (the
    warm-up made none of them: one of the same kind and count did, for mixed 1), while
    Mitsuba's kernel, the same for every scene, was made in the warm-up, as the first case
    of a run in one process made it for the rest."""
    from tools.harness import bench
    for kind in ("mixed", "spheres"):
        # (an empty cache each: mixed's warm-up is spheres 1, whose kernels it would hold)
        monkeypatch.setenv("DRJIT_CACHE_DIR", str(tmp_path / kind))
        case = bench.run_bench([1], [kind], columns=32, reps=1)["cases"][0]
        tr = case["tracers"]
        assert tr["rt_core-f32"]["compiled"] >= 1 and tr["rt_core-f64"]["compiled"] >= 1, kind
        assert tr["mitsuba"]["compiled"] == 0, (kind, tr["mitsuba"])


def test10b_a_case_that_fails_ends_the_run_in_one_line(tmp_path, monkeypatch):
    """A case's process that fails: its last line, named for the case, and its exit code
    where it is a user's error (2); its folder removed."""
    import tempfile
    from rt_core.usererror import InputError
    from tools.harness import bench
    from tools.harness.isolate import run_case
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(InputError) as e:
        run_case("bench nosuch N=1", "tools.harness.bench", "bench_case",
                 {"kind": "nosuch", "n": 1})
    msg = str(e.value)
    assert msg.startswith("bench nosuch N=1: its process failed (exit 1): ValueError: bench "
                          "scene must be one of") and "\n" not in msg, msg
    assert msg.endswith("; --one-process runs it here, with its traceback"), msg
    assert e.value.exit_code == 1 and os.listdir(tmp_path) == []
    # the error's own line, not what the process printed after it (at exit)
    mod = tmp_path.parent / f"{tmp_path.name}-mod"
    mod.mkdir()
    (mod / "late_words.py").write_text(
        "import atexit, sys\n"
        "atexit.register(lambda: print('a warning at exit', file=sys.stderr))\n"
        "def fails(**kw):\n    raise ValueError('the case broke')\n"
        "def quits(**kw):\n    sys.exit(0)\n"
        "def reads(**kw):\n    open('/nonexistent/scene.txt')\n"
        "def warns(**kw):\n    print('a warning of the case', file=sys.stderr)\n"
        "    return {'a': 1}\n")
    monkeypatch.setenv("PYTHONPATH", str(mod))
    with pytest.raises(InputError) as e:
        run_case("bench late", "late_words", "fails", {})
    assert str(e.value) == ("bench late: its process failed (exit 1): ValueError: the case "
                            "broke; --one-process runs it here, with its traceback")
    assert os.listdir(tmp_path) == []
    # a process that ends well without a result has failed all the same (not exit 0)
    with pytest.raises(InputError) as e:
        run_case("bench quits", "late_words", "quits", {})
    assert e.value.exit_code == 1 and "its process failed (exit 1)" in str(e.value)
    # a file error worded as the command line words it in one process, its code kept
    with pytest.raises(InputError) as e:
        run_case("bench reads", "late_words", "reads", {})
    assert str(e.value) == ("bench reads: its process failed (exit 2): /nonexistent/scene.txt: "
                            "no such file or directory") and e.value.exit_code == 2
    # what a case that succeeds says on stderr is passed on, as in one process
    import contextlib
    import io
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert run_case("bench warns", "late_words", "warns", {})["a"] == 1
    assert "a warning of the case" in err.getvalue()
    assert os.listdir(tmp_path) == []
    if not _has_cuda():
        # (the backend reaches the case's process: there, no CUDA device)
        with pytest.raises(InputError) as e:
            bench.run_bench([1], ["mixed"], columns=32, reps=1, backend_name="cuda")
        assert "CUDA" in str(e.value) and e.value.exit_code == 2, str(e.value)
        assert os.listdir(tmp_path) == []


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    stat = f.read()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def _start_long_bench(tmp_path):
    """rtval bench on a long case, once that case's process runs: (the process, its child)."""
    import time
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "bench", "--objects", "4096",
                          "--scenes", "spheres", "--reps", "500", "--keep-cache"],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "TMPDIR": str(tmp_path)})
    t0 = time.monotonic()
    try:
        while not (kids := _children(p.pid)):
            assert p.poll() is None and time.monotonic() - t0 < 120, "no case's process"
            time.sleep(0.05)
    except BaseException:
        p.kill()
        p.communicate()
        raise
    time.sleep(1.0)                     # (well into its imports or its case)
    return p, kids


def _gone(pids, within: float = 20.0) -> bool:
    import time
    t0 = time.monotonic()
    while any(os.path.exists(f"/proc/{k}") for k in pids):
        if time.monotonic() - t0 > within:
            return False
        time.sleep(0.05)
    return True


def test10c_sigterm_ends_the_cases_process_too(tmp_path):
    """SIGTERM to rtval bench while a case runs in its own process: exit 143 in one line,
    the case's process gone, its folder removed.  SIGKILL to rtval bench: the case's
    process dies with it (the kernel's parent-death signal), not running on alone."""
    import signal
    p, kids = _start_long_bench(tmp_path)
    try:
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
        assert p.returncode == 128 + signal.SIGTERM and "Traceback" not in err, err
        assert err.strip().splitlines()[-1] == "rtval: terminated by SIGTERM", err
        assert _gone(kids, 0.0)
        assert not [n for n in os.listdir(tmp_path) if n.startswith("rtval-case-")]
    finally:
        p.kill()
        p.communicate()
    p, kids = _start_long_bench(tmp_path)
    try:
        p.kill()
        p.communicate(timeout=60)
        assert _gone(kids), "the case's process outlived rtval bench's SIGKILL"
        # its folder stays, and the next run's first case removes it
        left = [n for n in os.listdir(tmp_path) if n.startswith("rtval-case-")]
        assert len(left) == 1, left
        r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--objects", "1",
                            "--scenes", "spheres", "--columns", "32", "--reps", "1",
                            "--keep-cache"], cwd=REPO, capture_output=True, text=True,
                           timeout=300, env={**os.environ, "TMPDIR": str(tmp_path)})
        assert r.returncode == 0, r.stderr
        assert not [n for n in os.listdir(tmp_path) if n.startswith("rtval-case-")]
    finally:
        for k in kids:
            with __import__("contextlib").suppress(OSError):
                os.kill(k, signal.SIGKILL)


@pytest.mark.parametrize("one", [False, True], ids=["default", "one-process"])
def test10d_the_command_line_picks_where_cases_run(tmp_path, one):
    """rtval bench runs each case in its own process unless --one-process, both modes; the
    JSON says which, and each case its process."""
    for mode in ([], ["--shaded", "--tracers", "rt_core-f32", "mitsuba"]):
        out = tmp_path / "b.json"
        r = subprocess.run([sys.executable, "-m", "tools.cli", "bench", *mode, "--objects", "1",
                            "--scenes", "spheres", "--columns", "32", "--reps", "1",
                            "--keep-cache", "-o", str(out)] + (["--one-process"] if one else []),
                           cwd=REPO, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        res = json.loads(out.read_text())
        assert res["meta"]["cases_in"] == ("one process" if one else
                                           "a process each (after a warm-up case there)")
        assert all(("pid" in c) != one for c in res["cases"]), res["cases"]
