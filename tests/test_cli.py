"""The command line's manners: --version, "did you mean", outputs named for what they hold, a
PASS/FAIL word, digits that tell values apart, progress in a log, a closed pipe."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import json

import numpy as np
import pytest

from rt_core.exrio import write_exr

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "scenes" / "sphere.txt"


def rtval(*args, **kw):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO, timeout=300, **kw)


def test01_version():
    r = rtval("--version")
    assert r.returncode == 0 and r.stdout.startswith("rtval ")


def test01b_version_looked_up_only_when_asked(monkeypatch, capsys):
    """Building the parser (every command's start) does not look the version up (the
    package metadata and a git call: ~24 ms); --version does."""
    import tools.cli as cli
    asked = []
    monkeypatch.setattr(cli, "_version", lambda: asked.append(1) or "9.9")
    cli.build_parser().parse_args(["exr", "info", "x.exr"])
    assert asked == []
    with pytest.raises(SystemExit) as e:
        cli.build_parser().parse_args(["--version"])
    assert e.value.code == 0 and asked == [1] and capsys.readouterr().out == "rtval 9.9\n"


@pytest.mark.parametrize("args, said", [
    (("rendr", SPHERE), "invalid choice: 'rendr'"),
    (("render", SPHERE, "--colums", 10, "-o", "x.exr"), "unrecognized option --colums"),
    (("render", SPHERE, "--columns", 10, "--precision", "f65"), "invalid choice: 'f65'"),
    (("exr", "stat", "a.exr"), "invalid choice: 'stat'"),
], ids=["command", "option-before-required", "choice", "subcommand"])
def test02_did_you_mean(args, said):
    r = rtval(*args)
    err = r.stderr.strip()
    assert r.returncode == 64 and len(err.splitlines()) == 1, err
    want = {"rendr": "render", "--colums": "--columns", "f65": "f64", "stat": "stats"}
    typo = next(t for t in want if t in map(str, args))
    assert said in err and f"(did you mean {want[typo]}?)" in err, err


def test02a_no_did_you_mean_for_a_word_alike_only_in_its_dashes():
    """'--bogus' was 'close' to --verbose by its two dashes (a student's review)."""
    r = rtval("check", SPHERE, "--bogus")
    assert r.returncode == 64 and "unrecognized option --bogus" in r.stderr and \
        "did you mean" not in r.stderr, r.stderr


@pytest.mark.parametrize("args, said", [
    (("check", SPHERE, "--run", "x {scene} {out}", "--columns", 8, "--timeout", 0),
     "--timeout: must be > 0"),
    # (a negative number read 'must be >= 0', which 0 is not)
    (("check", SPHERE, "--run", "x {scene} {out}", "--columns", 8, "--timeout", -1),
     "--timeout: must be > 0, got -1"),
    (("render", SPHERE, "--columns", 8, "--ppm", "x.ppm", "--texture-dir", "no/such/dir"),
     "--texture-dir: no directory 'no/such/dir'"),
    # (a robustness review: each was a traceback, or a run that grew without bound)
    (("check", SPHERE, "--run", "x {scene} {out}", "--columns", 8, "--timeout", 2200000),
     "--timeout: at most 1e+06 seconds"),
    (("bench", "--threads", 99999), "--threads: at most 1024"),
    (("bench", "--objects", 99999999), "--objects: at most 65536"),
    (("bench", "--shaded", "--lights", 99999999), "--lights: at most 64"),
    (("validate", SPHERE, "--workers", 200), "--workers: at most 64 local worker processes"),
    (("stability", "--quick", "--seeds", 99999999999), "--seeds: at most 1000"),
    # (a review: each was a TypeError traceback from Dask, exit 1)
    (("stability", "--quick", "--scheduler", "tls://127.0.0.1:1"), "over tcp:// only"),
    (("validate", SPHERE, "--scheduler", "ucx://127.0.0.1:1"), "over tcp:// only"),
    # an empty value was taken as not given: no report, exit 0
    (("check", SPHERE, SPHERE, "--report", ""), "argument --report: an empty value"),
    # one column or row under corner sampling: a usage error in every command (it was exit 2
    # in some, 64 in check --run)
    (("render", SPHERE, "--columns", 1), "--columns: 1 column: the course's corner sampling"),
    (("render", SPHERE, "--columns", 8, "--rows", 1), "--rows: 1 row: the course's corner"),
    (("compare", SPHERE, "--columns", 1), "or --sampling centers"),
    (("check", SPHERE, SPHERE, "--columns", 1), "--columns: 1 column"),
    (("convert", SPHERE, "--columns", 1, "-o", "x.xml"), "--columns: 1 column"),
    (("validate", SPHERE, "--columns", 1), "--columns: 1 column"),
    (("report", SPHERE, "--columns", 8, 1), "--columns: 1 column"),
    (("bench", "--command", "--command-columns", 1), "--command-columns: 1 column"),
    # rules Mitsuba's course integrator cannot apply: refused, not recorded as applied (a
    # review: the XML said ties=last and rendered the first object's colour)
    (("convert", SPHERE, "--columns", 8, "--shading", "--rules", "ties=last,edges=open", "-o",
      "x.xml"), "--rules ties=last, edges=open: the course integrator has no parameter"),
    # render's options that would do nothing (accepted, no effect: a review; bench says so)
    (("render", SPHERE, "--columns", 8, "-o", "x.exr", "--max-dist", 30),
     "--max-dist not used: --max-dist and --texture-dir go with the shaded image"),
    (("render", SPHERE, "--columns", 8, "--ppm", "x.ppm", "--compression", "zip"),
     "--compression not used"),
    # an option beyond float32 is the option's fault, not the scene's (exit 2 before)
    (("convert", SPHERE, "--columns", 8, "--shading", "--max-dist", "1e39", "-o", "x.xml"),
     "--max-dist 1e+39: beyond float32"),
], ids=["timeout-0", "timeout-negative", "texture-dir", "timeout-huge", "threads", "objects", "lights",
        "workers", "seeds", "tls", "ucx", "empty", "render-1-column", "render-1-row", "compare", "check", "convert",
        "validate", "report", "bench-command", "convert-rules", "render-max-dist",
        "render-compression", "convert-max-dist"])
def test02b_invalid_option_values(args, said):
    r = rtval(*args)
    err = r.stderr.strip()
    assert r.returncode == 64 and len(err.splitlines()) == 1 and said in err, err


@pytest.mark.parametrize("opt, name, other", [("-o", "x.png", "--png"), ("--png", "z.exr", "-o"),
                                              ("--ppm", "y.png", "--png")])
def test03_an_output_is_named_for_what_it_holds(tmp_path, opt, name, other):
    r = rtval("render", SPHERE, "--columns", 10, opt, tmp_path / name)
    assert r.returncode == 64 and f"or use {other}" in r.stderr and not (tmp_path / name).exists()


def test04_compare_says_pass_and_survives_a_closed_pipe():
    r = rtval("compare", SPHERE, "--columns", 32)
    assert r.returncode == 0 and r.stdout.strip().splitlines()[-1].startswith(f"PASS {SPHERE}")
    r = subprocess.run(f"{sys.executable} -m tools.cli compare {SPHERE} --columns 32 --json "
                       "| head -1; exit ${PIPESTATUS[0]}", shell=True, executable="/bin/bash",
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0 and "Broken pipe" not in r.stderr and r.stdout.strip() == "["


def test04b_a_reader_that_stops_early_keeps_the_verdict_and_the_reports(tmp_path):
    """rtval check behind a reader that stops at once (``| true``): the failing verdict's exit
    1 and the --junit file, as without the pipe (a helper's review: exit 0, no JUnit file;
    exr diff's FAILURE 2 became 0 too)."""
    wrong = tmp_path / "sphere.ppm"
    assert rtval("render", REPO / "scenes" / "plane.txt", "--columns", 24, "--ppm",
                 wrong).returncode == 0
    junit = tmp_path / "j.xml"
    # (the reader exits before rtval's first write: every run's write meets a closed pipe)
    r = subprocess.run(f"{sys.executable} -m tools.cli check --images {tmp_path} {SPHERE} "
                       f"--junit {junit} | true; exit ${{PIPESTATUS[0]}}", shell=True,
                       executable="/bin/bash", capture_output=True, text=True, cwd=REPO,
                       timeout=300)
    assert r.returncode == 1 and "Broken pipe" not in r.stderr, r.stderr
    assert junit.is_file() and 'failures="1"' in junit.read_text()
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    write_exr(str(a), {"depth.Z": np.zeros((4, 4), np.float32)})
    write_exr(str(b), {"depth.Z": np.ones((4, 4), np.float32)})
    r = subprocess.run(f"{sys.executable} -m tools.cli exr diff {a} {b} | true; "
                       "exit ${PIPESTATUS[0]}", shell=True, executable="/bin/bash",
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 2 and "Broken pipe" not in r.stderr, r.stderr


def test04c_ctrl_c_while_the_libraries_load_is_one_line(monkeypatch, capsys):
    """Ctrl-C while Dr.Jit's import runs, before the command's own handling: the import
    broken off raised NameError (exit 1, a failing scene to check's callers, 31 lines of
    traceback; a helper's review); the interrupt is found behind it, exit 130, one line."""
    from tools import cli

    def interrupted_import(argv):
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as e:
                raise ImportError("Encountered an error while initializing the extension.") \
                    from e
        except ImportError:
            raise NameError("name '_drjit_ext' is not defined")
    monkeypatch.setattr(cli, "_main", interrupted_import)
    assert cli.main(["check", "a", "b"]) == 130
    assert capsys.readouterr().err == "rtval: interrupted\n"

    def plain(argv):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "_main", plain)
    assert cli.main([]) == 130

    def bug(argv):
        raise NameError("a bug of ours")
    monkeypatch.setattr(cli, "_main", bug)
    with pytest.raises(NameError):
        cli.main([])


def test05_worst_pixel_values_are_told_apart(tmp_path):
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    base = np.full((4, 4), 10.2259, np.float32)
    write_exr(str(a), {"depth.Z": base})
    other = base.copy()
    other[1, 2] = np.nextafter(other[1, 2], np.float32(20))    # one float32 ulp
    write_exr(str(b), {"depth.Z": other})
    r = rtval("exr", "diff", a, b)
    line = next(ln for ln in r.stdout.splitlines() if "values are" in ln)
    va, vb = line.split("values are ")[1].split(" vs ")
    # (9 significant digits here: enough to tell two float32 values apart, and each reads
    # back to its float32)
    assert va != vb and np.float32(va) == base[1, 2] and np.float32(vb) == other[1, 2]


def test06_validate_reports_progress_in_a_log(tmp_path):
    r = rtval("validate", SPHERE, "--columns", 24, "--precision", "f32", "-o", tmp_path)
    assert r.returncode == 0, r.stderr
    # rays, camera and the shaded course image
    assert "rtval validate: 3/3 comparisons (100%), 0 failed" in r.stderr
    assert "skipped: none" in r.stderr
    # where the time went (tools/harness/timing.py): every phase that ran is counted, and the
    # split in report.json is what the summary line prints
    split = json.loads((tmp_path / "report.json").read_text())["time_split"]
    rows = json.loads((tmp_path / "report.json").read_text())["results"]
    for phase in ("rt_core", "mitsuba", "classify", "other"):
        assert all(r["seconds"][phase] > 0 for r in rows), phase
        assert split["seconds"][phase] == pytest.approx(
            sum(r["seconds"][phase] for r in rows), abs=2e-3)
    assert sum(split["share"].values()) == pytest.approx(1, abs=1e-3)
    assert f"Mitsuba {100 * split['share']['mitsuba']:.0f}%" in r.stderr


def test07_convert_takes_shade_like_render(tmp_path):
    r = rtval("convert", REPO / "scenes" / "shade_spot.txt", "--columns", 41, "--rows", 31,
              "--shade", "-o", tmp_path / "s.xml")
    assert r.returncode == 0, r.stderr
    assert 'type="spot"' in (tmp_path / "s.xml").read_text()


@pytest.mark.parametrize("cmd", [("render", SPHERE, "--columns", 8, "-o"),
                                 ("convert", SPHERE, "--columns", 8, "-o")])
def test08_a_missing_directory_is_not_created(tmp_path, cmd):
    out = tmp_path / "no" / "such" / ("x.exr" if cmd[0] == "render" else "x.xml")
    r = rtval(*cmd, out)
    assert r.returncode == 2 and "no directory" in r.stderr and "create it first" in r.stderr
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize("cmd", [("validate", SPHERE, "--columns", 8, "--shaded-columns", 0),
                                 ("compare", SPHERE, "--columns", 8),
                                 ("check", SPHERE, SPHERE.with_suffix(".ppm")),
                                 ("stability", "--quick")])
def test08b_junit_into_a_missing_directory_is_refused_first(tmp_path, cmd):
    """--junit names a file: its directory is not made (it was, for all three), and the
    refusal comes before any work."""
    r = rtval(*cmd, "--junit", tmp_path / "no" / "such" / "j.xml", "-o" if cmd[0] == "validate"
              else "--json", *([tmp_path / "v"] if cmd[0] == "validate" else []))
    assert r.returncode == 2 and "no directory" in r.stderr and "create it first" in r.stderr
    assert not (tmp_path / "no").exists() and not (tmp_path / "v").exists()


@pytest.mark.parametrize("cmd", [("compare", SPHERE, "--columns", 8),
                                 ("validate", SPHERE, "--columns", 8, "--shaded-columns", 0)])
def test08c_report_where_nothing_can_be_written_is_refused_first(tmp_path, cmd):
    """--report DIR in /proc: refused before the comparisons run (it failed after them,
    with 'no such file or directory')."""
    r = rtval(*cmd, "--report", "/proc/rtval-report", "-o" if cmd[0] == "validate" else
              "--json", *([tmp_path / "v"] if cmd[0] == "validate" else []))
    assert r.returncode == 2 and "cannot create a file in /proc" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Mitsuba" not in r.stderr
    assert not (tmp_path / "v").exists() and r.stdout == ""


def test09_junit_for_validate_and_compare(tmp_path):
    import xml.etree.ElementTree as ET
    j = tmp_path / "v.xml"
    r = rtval("validate", SPHERE, "--columns", 24, "--precision", "f32", "-o", tmp_path / "v",
              "--junit", j, "--shaded-columns", 0)
    assert r.returncode == 0, r.stderr
    suite = ET.parse(j).getroot()
    assert suite.get("name") == "rtval validate" and suite.get("tests") == "2"
    assert suite.get("failures") == "0" and suite.find("properties") is not None
    assert sorted(c.get("name") for c in suite.iter("testcase")) == [
        "sphere.camera.f32", "sphere.rays.f32"]
    j = tmp_path / "c.xml"
    assert rtval("compare", SPHERE, "--columns", 24, "--mode", "rays", "--junit", j
                 ).returncode == 0
    assert [c.get("name") for c in ET.parse(j).getroot().iter("testcase")] == \
        ["sphere.rays.f32"]


def test10_junit_marks_failures_and_skips():
    import xml.etree.ElementTree as ET
    from tools.harness.validate import comparison_cases, skip_case
    from tools.harness.junit import junit_xml
    from tools.harness.validate import Skipped
    row = {"scene": "scenes/x.txt", "mode": "rays", "precision": "f64", "rt_core_ms": 1.0,
           "mitsuba_ms": 2.0, "classes": {"agree": 10, "unexplained": 3}, "columns": 4,
           "rows": 3, "depth": {"max_rel": 1e-3, "over_bound": 2}, "ok": False,
           "unexplained": 3, "evidence": ["out/x.rays.f64.classes.exr"],
           "seconds": {"rt_core": 0.001, "mitsuba": 0.002}}
    cases = comparison_cases([row, dict(row, ok=True, mode="camera")], "rtval.validate")
    cases.append(skip_case(Skipped("c/bad.txt", "c/bad.txt:3:1: oops", "malformed")))
    suite = ET.fromstring(junit_xml("rtval validate", cases))
    # a skipped file is skipped, as the run passes without it (it was an error: CI went red
    # on a run that exited 0 and said PASS, a helper's review)
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors"),
            suite.get("skipped")) == ("3", "1", "0", "1")
    failure = suite.find("testcase/failure")
    assert "3 unexplained pixels" in failure.get("message") and "evidence" in failure.text
    assert suite.find("testcase/skipped").get("message").startswith("malformed: ")


def test10b_junit_names_are_unique_and_its_text_is_xml():
    """A case named twice in a class (a scene listed twice, two scenes of one file name) is
    numbered: CI tools merge cases of one class and name; a control character or a byte
    that is not UTF-8 in a name is written as \\xNN (the file was not XML: a helper's
    review)."""
    import xml.etree.ElementTree as ET
    from tools.harness.junit import Case, junit_xml
    suite = ET.fromstring(junit_xml("s", [Case("a.txt", "c"), Case("a.txt", "c"),
                                          Case("a.txt", "d"), Case("p\x01l\udcff.txt", "c",
                                                                   failure="x\x02")]).encode())
    names = [(c.get("classname"), c.get("name")) for c in suite.iter("testcase")]
    assert names == [("c", "a.txt"), ("c", "a.txt (2)"), ("d", "a.txt"),
                     ("c", "p\\x01l\\xff.txt")]
    assert suite.find("testcase/failure").get("message") == "x\\x02"


def test10c_two_scenes_of_one_name_keep_their_own_evidence():
    """validate's evidence files are named by the scene's stem: two scenes of one file name
    in different folders wrote each other's; they get their folders' names."""
    from tools.harness.validate import unique_stems
    got = unique_stems(["scenes/plane.txt", "x/dup/plane.txt", "scenes/sphere.txt",
                        "a/dup/plane.txt"])
    assert got["scenes/sphere.txt"] == "sphere"
    assert len({got[p] for p in ("scenes/plane.txt", "x/dup/plane.txt",
                                 "a/dup/plane.txt")}) == 3
    assert got["scenes/plane.txt"] == "scenes__plane"


def test11_an_option_value_may_start_with_dashes(tmp_path):
    """The pre-scan for misspelt options must not take a value for an option: a tracer
    command that starts with '--' is a value of --run."""
    r = rtval("check", SPHERE, "--run", "--gpu {scene} {out}", "--columns", 16)
    assert r.returncode != 64 and "unrecognized" not in r.stderr, r.stderr


def test12b_dr_jit_loads_after_before_import():
    """bench and report pick a fresh kernel cache in ``before_import``, which works only
    while Dr.Jit is not loaded: main imported rt_core first for a while (its file tracking),
    and their first calls reported the shared cache's hits as compilation (a review)."""
    code = ("import sys, tools.cli as c, tools.cmd_bench as b\n"
            "b.fresh_kernel_cache = lambda keep: print('drjit' in sys.modules)\n"
            "b.run = lambda args: 0\n"
            "c.main(['bench', '--objects', '1'])")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stdout + r.stderr


def test12_building_the_parser_loads_no_dr_jit():
    """`rtval --help` and the parser of every command load neither Dr.Jit nor Mitsuba (0.2 s
    and more at every start); tools.options' copy of --code27's choices is rt_core's."""
    code = ("import sys, tools.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('drjit', 'mitsuba', 'rt_core') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
    from rt_core.kinds_planar import CODE27_CHOICES
    from tools.options import CODE27_CHOICES as copy
    assert tuple(copy) == tuple(CODE27_CHOICES)


def test13_in_env_runs_the_command_where_it_was_called(tmp_path):
    """tools/in-env.sh sets up in the repository but runs the command in the caller's
    directory, so that its relative paths are the caller's."""
    (tmp_path / "here.txt").write_text("x")
    r = subprocess.run([str(REPO / "tools" / "in-env.sh"), "python", "-c",
                        "import os; print(os.getcwd()); print(open('here.txt').read())"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [str(tmp_path), "x"]


def test14_in_env_finds_the_installed_llvm_whatever_ldconfig_prints_after_it(tmp_path):
    """have_llvm under pipefail: with grep -q, grep quit at the LLVM line and an ldconfig
    still writing died of SIGPIPE, failing the pipeline (3 in 200 calls on a loaded
    machine), and the script reinstalled LLVM with apt-get.  Here a stand-in ldconfig
    prints the library first and then more than a pipe holds, so that race always
    happens."""
    fake = tmp_path / "ldconfig"
    fake.write_text("#!/bin/sh\necho '\tlibLLVM.so.19.1 (libc6,x86-64) => /lib/libLLVM.so.19.1'\n"
                    "yes '\tlibfoo.so.1 (libc6,x86-64) => /lib/libfoo.so.1' | head -n 20000\n")
    fake.chmod(0o755)
    script = (REPO / "tools" / "in-env.sh").read_text()
    start = script.index("have_llvm()")
    func = script[start:script.index("; }", start) + 3]
    r = subprocess.run(["bash", "-c", f"set -o pipefail; {func}\n"
                        "for i in 1 2 3 4 5; do have_llvm || { echo missed; exit 1; }; done"],
                       capture_output=True, text=True, timeout=60,
                       env={**os.environ, "PATH": f"{tmp_path}:{os.environ['PATH']}"})
    assert r.returncode == 0, r.stdout + r.stderr


def test20_code27_where_a_message_suggests_it(tmp_path):
    """A scene whose code-27 line fits neither layout says 'force a layout with --code27';
    check, compare, validate, report and gallery had no such option (exit 64).  Each takes
    it now, and reads the scene with it, both readers alike."""
    scene = tmp_path / "c27.txt"
    scene.write_text("8 6\n0 0 3\n27\n1 1 1\n1 1 1\n0 0 0\n0 0 -5\n1 2\n0 0 1\n")
    ppm = tmp_path / "c27.ppm"
    r = rtval("render", scene, "--columns", 16, "--code27", "disk", "--ppm", ppm)
    assert r.returncode == 0, r.stderr
    r = rtval("check", scene, ppm)
    assert r.returncode == 2 and "force a layout with --code27" in r.stderr, r.stderr
    for args in (("check", scene, ppm), ("compare", scene, "--columns", 16),
                 ("validate", scene, "--columns", 16, "-o", tmp_path / "v"),
                 ("report", scene, "--columns", 16, "--quick", "-o", tmp_path / "r"),
                 ("gallery", scene, "--columns", 16, "-o", tmp_path / "g")):
        r = rtval(*args, "--code27", "disk")
        assert r.returncode == 0, (args, r.stderr[-500:])
