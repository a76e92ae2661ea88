"""Bad input and faults: one line naming the file, the documented exit code, no traceback, no
output or temporary file left behind (issue 16's reproducers, each first failing).

A full disk is ``/dev/full`` and, where this process may mount one, a 64 KiB tmpfs filled up;
a memory limit is an address-space rlimit on the child process.
"""
from __future__ import annotations

import contextlib
import os
import resource
import signal
import subprocess
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rt_core import backend
from rt_core.camera import make_camera
from rt_core.exrio import incomplete, read_exr, write_exr
from rt_core.memory import guard, render_bytes
from rt_core.outputs import TMP_PREFIX, WriteError, atomic_write
from rt_core.parser import parse_scene
from rt_core.render import render_image, render_tiled
from rt_core.rules import Rules
from rt_core.usererror import InputError

REPO = Path(__file__).resolve().parents[1]
SEED = REPO / "scenes" / "seed_fplane.txt"
from tests.tolerances import PRECISIONS  # noqa: E402


def rtval(*args, limit_as=None, timeout=120):
    def pre():
        if limit_as:
            resource.setrlimit(resource.RLIMIT_AS, (limit_as, limit_as))
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO, timeout=timeout,
                          preexec_fn=pre if limit_as else None)


def one_line(r, code: int, *needles):
    """The run failed with ``code`` and said so in one line containing ``needles``."""
    err = r.stderr.strip()
    assert r.returncode == code, (r.returncode, err)
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, (n, err)
    assert TMP_PREFIX not in err and ".tmp-" not in err, err     # the target, not a temporary
    return err


def scene_with_header(tmp_path, header: str) -> Path:
    lines = [ln for ln in SEED.read_text().splitlines() if not ln.startswith("#")]
    body = "\n".join(lines).replace("10 7.5", header, 1)
    p = tmp_path / "h.txt"
    p.write_text(body)
    return p


@pytest.fixture(scope="module")
def full_dir(tmp_path_factory):
    """A directory on a full file system (a 64 KiB tmpfs, filled)."""
    d = tmp_path_factory.mktemp("full")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)],
                       capture_output=True)
    if r.returncode:
        pytest.skip("cannot mount a small tmpfs here (not root, or no mount permission); "
                    "/dev/full covers the device case")
    with open(d / "fill", "wb") as f:
        try:
            f.write(b"\0" * (1 << 17))
        except OSError:
            pass
    yield d
    subprocess.run(["umount", str(d)], capture_output=True)


# --- 1. the default row count overflows --------------------------------------------------

@pytest.mark.parametrize("header,col", [("1e-320 6", 8), ("1e-300 1e300", 8), ("8 1e308", 3),
                                        ("1e-30 6", 7)])
def test01_overflowing_default_rows_is_one_line_at_the_window(tmp_path, header, col):
    p = scene_with_header(tmp_path, header)
    one_line(rtval("render", p, "--columns", 32, "-o", tmp_path / "x.exr"), 2,
             f"h.txt:2:{col}: header: world window", "give --rows")
    assert not (tmp_path / "x.exr").exists()
    # convert too (a review: a traceback at 1e-320, an XML of 1.9e32 rows that Mitsuba
    # cannot read at 1e-30, where render refused)
    one_line(rtval("convert", p, "--columns", 32, "-o", tmp_path / "x.xml"), 2,
             f"h.txt:2:{col}: header: world window", "give --rows")
    assert not (tmp_path / "x.xml").exists()


# --- 2, 3. a full disk: tracebacks and lost writes --------------------------------------------

@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
@pytest.mark.parametrize("opt,columns", [("-o", 32), ("-o", 4), ("--ppm", 4), ("--png", 32)])
def test02_dev_full_is_an_error_not_a_success(opt, columns):
    args = ["--rows", 3] if columns == 4 else []
    one_line(rtval("render", SEED, "--columns", columns, *args, opt, "/dev/full"), 2,
             "/dev/full: cannot write: no space left on device", "write elsewhere")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
@pytest.mark.parametrize("cmd,code", [(("exr", "info", "@"), 4), (("exr", "stats", "@"), 4),
                                      (("exr", "diff", "@", "@"), 4),
                                      (("check", SEED, "@"), 2), (("validate", "--help"), 2),
                                      (("render", SEED, "--columns", 8, "--json", "-o", "@j"),
                                       2)],
                         ids=["exr-info", "exr-stats", "exr-diff", "check", "help",
                              "render-json"])
def test02b_standard_output_on_a_full_disk(cmd, code, tmp_path):
    """Standard output on /dev/full: one line naming it and what to do (it read
    '[Errno 28] No space left on device', no file, no fix: a helper's review), exit 2, or
    exr's 4 for a file it cannot write (its 2 is diff's FAILURE: a diff of two identical
    images said so); render's --json report goes with its files, all or none (the EXR was
    left, announced)."""
    img = tmp_path / "i.ppm"
    rtval("render", SEED, "--columns", 8, "--ppm", img)
    args = [img if a == "@" else tmp_path / "j.exr" if a == "@j" else a for a in cmd]
    with open("/dev/full", "w") as full:
        r = subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)], cwd=REPO,
                           stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    one_line(r, code, "standard output: cannot write: no space left on device",
             "free some space or write elsewhere")
    assert not (tmp_path / "j.exr").exists()


@pytest.mark.parametrize("opt,name", [("-o", "x.exr"), ("--ppm", "x.ppm"), ("--png", "x.png")])
def test03_full_file_system_small_write_is_not_lost(full_dir, opt, name):
    r = rtval("render", SEED, "--columns", 4, "--rows", 3, opt, full_dir / name)
    one_line(r, 2, f"{full_dir / name}: cannot write: no space left on device")
    assert sorted(p.name for p in full_dir.iterdir()) == ["fill"]


def test03c_report_on_a_full_disk_leaves_nothing(full_dir, tmp_path):
    """rtval report wrote its PNG, then failed on its JSON: the PNG and the new directory
    stayed (a review).  Its three files are written together or not at all, and a directory
    it made for them is removed."""
    out = full_dir / "rep"
    r = rtval("report", SEED, "--columns", 16, "--sample", 10, "--reps", 1, "-o", out)
    last = r.stderr.strip().splitlines()[-1]          # (after its progress line)
    assert r.returncode == 2 and "Traceback" not in r.stderr and \
        "cannot write: no space left on device" in last, r.stderr
    assert not out.exists() and sorted(p.name for p in full_dir.iterdir()) == ["fill"]


def test03d_report_too_large_and_a_scene_with_objects_left_out(tmp_path):
    """rtval report had no memory guard (20000 columns: 23.7 GB, then the out-of-memory
    killer); and on a torus scene it measured the scene without the torus, said in its
    JSON rows only (a review)."""
    out = tmp_path / "big"
    one_line(rtval("report", SEED, "--columns", 200000, "-o", out), 2,
             "report 200000x150000 needs ~", "use --columns <= ")
    assert not out.exists()
    out = tmp_path / "torus"
    r = rtval("report", REPO / "scenes" / "torus.txt", "--columns", 16, "--sample", 20,
              "--reps", 1, "-o", out)
    assert r.returncode == 0, r.stderr
    assert "(note: left out of this Mitsuba comparison" in r.stderr
    assert "Measured without the objects Mitsuba has no shape for, in every configuration " \
        "(rt_core's and the oracle's too): line 11 torus." in (out / "report.md").read_text()


def test03b_full_temporary_folder_bench(full_dir, tmp_path, monkeypatch):
    """rtval bench runs each case in its own process, its files in a temporary folder (where
    Python's tempfile finds TMPDIR unwritable it takes another): a full one is one line,
    what to do, and nothing left there, on both sides."""
    import json
    import tempfile
    from rt_core.usererror import InputError
    from tools.harness.isolate import run_case
    top = full_dir / "top"                  # (its last free bytes too: a JSON is small)
    with open(top, "wb", buffering=0) as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 256)
    try:
        # the parent: the case's spec cannot be written
        monkeypatch.setattr(tempfile, "tempdir", str(full_dir))
        with pytest.raises(InputError) as e:
            run_case("bench spheres N=1", "builtins", "dict", {"a": 1})
        assert e.value.exit_code == 2 and "no space left on device" in str(e.value) and \
            "free some space there" in str(e.value), str(e.value)
        assert sorted(p.name for p in full_dir.iterdir()) == ["fill", "top"]
        # the case's process: its result cannot be written
        spec = tmp_path / "spec.json"
        spec.write_text(json.dumps({"module": "builtins", "function": "dict",
                                    "kwargs": {"a": 1}, "parent": os.getpid()}))
        r = subprocess.run([sys.executable, "-m", "tools.harness.isolate", str(spec),
                            str(full_dir / "case.json")], cwd=REPO, capture_output=True,
                           text=True, timeout=300)
        one_line(r, 2, "cannot write the case's result", "no space left on device",
                 "free some space there")
        assert sorted(p.name for p in full_dir.iterdir()) == ["fill", "top"]
    finally:
        top.unlink()


def test04_full_file_system_other_commands(full_dir, tmp_path):
    one_line(rtval("convert", SEED, "--columns", 41, "--rows", 31, "-o", full_dir / "s.xml"), 2,
             f"{full_dir / 's.xml'}: cannot write: no space left on device")
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    for p, c in ((a, 8), (b, 8)):
        assert rtval("render", SEED, "--columns", c, "-o", p).returncode == 0
    one_line(rtval("exr", "diff", a, b, "-o", full_dir / "d.exr"), 4,
             f"{full_dir / 'd.exr'}: cannot write")
    one_line(rtval("exr", "diff", a, b, "-o", "/dev/full"), 4, "/dev/full: cannot write")
    r = rtval("validate", SEED, "--columns", 16, "-o", full_dir / "v")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert f"{full_dir / 'v'}/" in r.stderr.strip().splitlines()[-1] and \
        "no space left on device" in r.stderr.strip().splitlines()[-1]
    one_line(rtval("gallery", SEED, "-o", full_dir / "g"), 2,
             f"{full_dir / 'g' / 'seed_fplane.png'}: cannot write: no space left on device")
    # nothing left: no file, no temporary, no directory the failed writes created
    assert sorted(p.name for p in full_dir.iterdir()) == ["fill"]


@pytest.mark.parametrize("argv", [
    ("validate", SEED, "--columns", 16, "-o", "/proc/rtval-v"),
    ("validate", SEED, "--columns", 16, "--junit", "/proc/v.xml"),
    ("bench", "--objects", 1, "--columns", 64, "-o", "/proc/b.json"),
    ("stability", "--quick", "--families", "parallel", "--serial", "--json", "/proc/s.json"),
    ("stability", "--quick", "--families", "parallel", "--serial", "-o", "/proc/rtval-s"),
    ("compare", SEED, "--columns", 16, "--junit", "/proc/c.xml"),
    ("report", "--quick", "-o", "/proc/rtval-r"),
    ("gallery", SEED, "--columns", 16, "-o", "/proc/rtval-g"),
    ("convert", SEED, "--columns", 16, "-o", "/proc/x.xml"),
    ("check", SEED, "x.ppm", "--junit", "/proc/j.xml"),
], ids=lambda a: " ".join(map(str, a[:1] + a[-2:-1])))
def test04g_outputs_refused_before_the_work(argv):
    """An output where no file can be created is one line and exit 2 before the command's
    work (it used to come after a whole validate, bench or stability run, whose other
    outputs were written by then)."""
    one_line(rtval(*argv, timeout=60), 2, "/proc/", "cannot create a file in /proc")


def test04g2_compare_default_evidence_is_not_probed():
    """compare writes its default evidence directory (out/compare) only when a comparison
    fails: run where nothing can be written (/proc), a passing compare exits 0; an
    --evidence given there is refused first."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    run = lambda *a: subprocess.run([sys.executable, "-m", "tools.cli", "compare", str(SEED),
                                     "--columns", "16", "--mode", "rays", *a], cwd="/proc",
                                    env=env, capture_output=True, text=True, timeout=120)
    r = run()
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    one_line(run("--evidence", "/proc/rtval-e"), 2, "cannot create a file in /proc")


def test04h_gallery_leaves_nothing_when_a_named_scene_fails(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text(SEED.read_text().splitlines()[0] + "\n")
    out = tmp_path / "gal" / "b"
    one_line(rtval("gallery", SEED, bad, "--columns", 16, "-o", out), 2, "bad.txt")
    assert not (tmp_path / "gal").exists()


def test04b_several_outputs_all_or_none(full_dir, tmp_path):
    """render -o (a good directory) --ppm (a full one): the EXR, written first, is not left
    behind when the PPM fails; with both writable both are there."""
    exr, ppm = tmp_path / "x.exr", full_dir / "x.ppm"
    one_line(rtval("render", SEED, "--columns", 4, "--rows", 3, "-o", exr, "--ppm", ppm), 2,
             f"{ppm}: cannot write: no space left on device")
    assert not exr.exists() and sorted(p.name for p in tmp_path.iterdir()) == []
    assert sorted(p.name for p in full_dir.iterdir()) == ["fill"]
    r = rtval("render", SEED, "--columns", 4, "--rows", 3, "-o", exr, "--ppm", tmp_path / "x.ppm")
    assert r.returncode == 0 and exr.exists() and (tmp_path / "x.ppm").exists()


def test04c_together_renames_all_or_none(tmp_path):
    """outputs.together: a failure after a successful write removes that write's temporary
    (and the directory it created) and renames nothing; success renames every file."""
    from rt_core.outputs import together
    a, b = tmp_path / "new" / "a.txt", tmp_path / "b.txt"
    with pytest.raises(WriteError):
        with together():
            atomic_write(a, lambda tmp: Path(tmp).write_text("a"))
            assert not a.exists()               # held until the block ends
            atomic_write(b, lambda tmp: Path(tmp).write_text(""))    # empty: refused
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    with together():
        atomic_write(a, lambda tmp: Path(tmp).write_text("a"))
        atomic_write(b, lambda tmp: Path(tmp).write_text("b"))
    assert a.read_text() == "a" and b.read_text() == "b"
    assert sorted(p.name for p in a.parent.iterdir()) == ["a.txt"]


def test04d_a_failed_rename_at_the_end_of_together(tmp_path, monkeypatch):
    """A rename that fails when together() ends: one WriteError naming the file, and no
    temporary left (the earlier rename stands: it cannot be undone)."""
    from rt_core import outputs
    real = os.replace

    def replace(src, dst):
        if str(dst).endswith("b.txt"):
            raise PermissionError(1, "Operation not permitted")
        return real(src, dst)
    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(WriteError, match=r"b\.txt: .*operation not permitted"):
        with outputs.together():
            atomic_write(tmp_path / "a.txt", lambda tmp: Path(tmp).write_text("a"))
            atomic_write(tmp_path / "b.txt", lambda tmp: Path(tmp).write_text("b"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]



def test04f_a_failed_rename_names_the_file_as_given(tmp_path, monkeypatch):
    """The rename of a single atomic_write (outside together()) failing: one WriteError with
    the output's name as the user gave it (through a symlinked folder, not its target), and
    no temporary left; before, a bare PermissionError named no file."""
    from rt_core import outputs
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")

    def replace(src, dst):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(outputs.os, "replace", replace)
    given = str(tmp_path / "link" / "b.txt")
    with pytest.raises(WriteError, match=r"link/b\.txt: .*operation not permitted") as e:
        atomic_write(given, lambda tmp: Path(tmp).write_text("b"))
    assert "real" not in str(e.value)
    assert list((tmp_path / "real").iterdir()) == []

def test05b_every_cut_of_an_exr_is_incomplete_never_an_exception(tmp_path):
    p = tmp_path / "a.exr"
    write_exr(str(p), {"R": np.random.default_rng(2).random((40, 24)), "G": np.ones((40, 24))})
    data = p.read_bytes()
    for n in range(len(data)):                 # (a chunk header cut short used to raise)
        p.write_bytes(data[:n])
        assert incomplete(str(p)) is not None, n


@pytest.mark.parametrize("cut", [0, 9, 200, 0.5, -1])
def test05_incomplete_exr_is_detected(tmp_path, cut):
    p = tmp_path / "a.exr"
    write_exr(str(p), {"R": np.random.default_rng(1).random((40, 30))})
    assert incomplete(str(p)) is None
    data = p.read_bytes()
    n = int(len(data) * cut) if isinstance(cut, float) else (len(data) + cut if cut < 0 else cut)
    p.write_bytes(data[:n])
    assert incomplete(str(p)) is not None


def test06_a_short_write_is_refused_and_leaves_nothing(tmp_path):
    good = tmp_path / "good.exr"
    write_exr(str(good), {"R": np.ones((20, 20), np.float32)})
    data = good.read_bytes()
    target = tmp_path / "out.exr"
    with pytest.raises(WriteError, match=r"out\.exr: cannot write: the file is truncated"):
        atomic_write(target, lambda tmp: Path(tmp).write_bytes(data[:-10]), verify=incomplete)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.exr"]


def test06b_write_exr_checks_what_the_binding_wrote(tmp_path, monkeypatch):
    """The binding loses a failed last flush silently (a small EXR on a full disk): a file
    whose tail is missing must be an error, not a success."""
    import OpenEXR
    import rt_core.exrio as exrio
    real = OpenEXR.File

    class LosesTail:
        def __init__(self, *a):
            self.f = real(*a)

        def write(self, path):
            self.f.write(path)
            with open(path, "r+b") as fh:
                fh.truncate(os.path.getsize(path) - 100)
    monkeypatch.setattr(exrio.OpenEXR, "File", LosesTail)
    with pytest.raises(WriteError, match=r"o\.exr: cannot write: .*truncated"):
        write_exr(str(tmp_path / "o.exr"), {"R": np.ones((30, 20))})
    assert os.listdir(tmp_path) == []


# --- 4. deep and multi-part EXRs -----------------------------------------------------------

@pytest.fixture(scope="module")
def odd_exrs(tmp_path_factory):
    from tests.exrgen import write_deep, write_parts
    d = tmp_path_factory.mktemp("exr")
    write_deep(d / "deep.exr")
    write_parts(d / "multi.exr", [("a", "R", np.full((4, 5), 1.0)),
                                  ("b", "G", np.full((4, 5), 2.0))])
    return d


@pytest.mark.parametrize("cmd", [("stats",), ("preview", "-o", "p.png"), ("diff", "@")])
def test07_deep_exr_is_refused_in_one_line(odd_exrs, tmp_path, cmd):
    deep = odd_exrs / "deep.exr"
    args = [deep if a == "@" else (tmp_path / a if a.endswith(".png") else a) for a in cmd]
    one_line(rtval("exr", cmd[0], deep, *args[1:]), 4, "deep.exr: a deep EXR", "--flatten")
    assert not (tmp_path / "p.png").exists()


def test08_deep_info_and_every_part_of_a_multi_part_file(odd_exrs):
    r = rtval("exr", "info", odd_exrs / "deep.exr")
    assert r.returncode == 0 and "deep FLOAT" in r.stdout and "deepscanline" in r.stdout
    r = rtval("exr", "info", odd_exrs / "multi.exr")
    assert r.returncode == 0 and "parts (2)" in r.stdout and "a.R" in r.stdout \
        and "b.G" in r.stdout
    r = rtval("exr", "stats", odd_exrs / "multi.exr")
    rows = {ln.split()[0]: ln.split() for ln in r.stdout.splitlines()[2:]}
    assert r.returncode == 0 and rows["a.R"][3] == "1" and rows["b.G"][3] == "2"



@pytest.mark.parametrize("cmd, code", [
    (("check", "s.txt", "i.ppm", "--junit", "s.txt"), 2),
    (("compare", "s.txt", "--columns", 8, "--junit", "s.txt"), 2),
    (("validate", "s.txt", "--junit", "s.txt"), 2),
    (("render", "link.txt", "--columns", 8, "-o", "s.txt"), 2),     # the same file, linked
    (("exr", "diff", "a.exr", "b.exr", "-o", "a.exr"), 4),
    (("exr", "preview", "i.ppm", "-o", "i.ppm"), 4)],
    ids=["check-junit", "compare-junit", "validate-junit", "render-link", "exr-diff", "preview"])
def test07c_an_output_naming_an_input_is_refused(cmd, code, tmp_path):
    """An output option naming a file the command reads replaced it, exit 0 (the scene
    became JUnit XML, image A the difference image): refused before anything runs, one line,
    the input as it was (a helper's review)."""
    shutil.copy(SEED, tmp_path / "s.txt")
    os.link(tmp_path / "s.txt", tmp_path / "link.txt")
    for name, args in (("a.exr", ("-o", "a.exr")), ("b.exr", ("-o", "b.exr")),
                       ("i.ppm", ("--ppm", "i.ppm"))):
        r = subprocess.run([sys.executable, "-m", "tools.cli", "render", str(tmp_path / "s.txt"),
                            "--columns", "8", *args[:1], str(tmp_path / args[1])],
                           cwd=REPO, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    r = subprocess.run([sys.executable, "-m", "tools.cli", *map(str, cmd)], cwd=tmp_path,
                       capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    err = one_line(r, code, "names the input", "write the output elsewhere")
    assert "cannot write" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before



def test07e_inputs_read_on_the_way_are_not_replaced_and_neighbours_are_fine(tmp_path):
    """A review of the refusal: a scene's texture is an input too (--ppm textures/x.ppm
    replaced it: refused at the write, as a file the command read); a hit dump is an input
    of check; and with --images DIR only the scenes' images there are refused, a JUnit
    file beside them is fine."""
    import shutil as sh
    sh.copytree(REPO / "scenes" / "textures", tmp_path / "textures")
    sh.copy(REPO / "scenes" / "textured.txt", tmp_path)
    tex = tmp_path / "textures" / "tiles4x3.ppm"
    before = tex.read_bytes()
    r = subprocess.run([sys.executable, "-m", "tools.cli", "render", str(tmp_path /
                        "textured.txt"), "--columns", "40", "--ppm", str(tex)], cwd=REPO,
                       capture_output=True, text=True)
    one_line(r, 2, "tiles4x3.ppm: cannot write: it is a file this command read")
    assert tex.read_bytes() == before
    img, hits = tmp_path / "i.ppm", tmp_path / "h.txt"
    rtval("render", SEED, "--columns", 8, "--ppm", img)
    hits.write_text("0 0 -1 0\n")
    r = rtval("check", SEED, img, "--hits", hits, "--junit", hits)
    one_line(r, 2, "--junit names the input")
    assert hits.read_text() == "0 0 -1 0\n"
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    sh.copy(img, imgs / f"{SEED.stem}.ppm")
    r = rtval("check", "--images", imgs, SEED, "--junit", imgs / "report.xml")
    assert r.returncode in (0, 1) and (imgs / "report.xml").exists(), r.stderr
    r = rtval("check", "--images", imgs, SEED, "--junit", imgs / f"{SEED.stem}.png")
    one_line(r, 2, "is the image of a scene in the --images directory")


def test07f_standard_output_closed(tmp_path):
    """Standard output closed (>&-): Python makes sys.stdout None and print() skips it; the
    full-disk wrapper turned that into an AttributeError traceback (a review)."""
    for args in (["render", str(SEED), "--columns", "8", "--ppm", str(tmp_path / "x.ppm")],
                 ["--help"]):
        r = subprocess.run([sys.executable, "-m", "tools.cli", *args], cwd=REPO,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                           preexec_fn=lambda: os.close(1))
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr


def test07d_file_names_that_are_not_utf8(tmp_path):
    """A scene whose name is not UTF-8 renders, its name in the provenance with the odd byte
    escaped (the EXR's header would not take it: the error blamed the output); an image of
    such a name is one line, exit 2 (4 for rtval exr), not a TypeError from OpenImageIO (a
    helper's review)."""
    d = os.fsencode(tmp_path)
    scene, image, out = d + b"/sc\xff.txt", d + b"/img\xff.ppm", tmp_path / "o.exr"
    with open(scene, "wb") as f:
        f.write(SEED.read_bytes())
    r = subprocess.run([sys.executable.encode(), b"-m", b"tools.cli", b"render", scene,
                        b"--columns", b"8", b"-o", os.fsencode(out), b"--ppm", image],
                       cwd=REPO, capture_output=True)
    assert r.returncode == 0, r.stderr
    _, hdr = read_exr(out)
    assert hdr["rtval.scene"].endswith("sc\\xff.txt")
    for cmd, code in (([b"check", scene, image], 2), ([b"exr", b"info", image], 4)):
        r = subprocess.run([sys.executable.encode(), b"-m", b"tools.cli", *cmd], cwd=REPO,
                           capture_output=True)
        err = r.stderr.decode("utf-8", "replace").strip()
        assert r.returncode == code and len(err.splitlines()) == 1, err
        assert "img\\xff.ppm: the file name is not UTF-8" in err and "rename" in err, err

# --- 5. memory --------------------------------------------------------------------------------

def test09_too_large_is_refused_before_allocating():
    t0 = time.monotonic()
    r = rtval("compare", SEED, "--columns", 20000, "--mode", "rays")
    err = one_line(r, 2, "compare 20000x15000 needs ~", "available", "use --columns <= ")
    assert time.monotonic() - t0 < 60, "refused only after allocating"
    suggested = int(err.rsplit("<= ", 1)[1].split()[0])
    assert 2 <= suggested < 20000



@pytest.mark.parametrize("cmd, said", [
    (("compare", "--shaded", SEED, "--columns", 20000),
     ("compare --shaded 20000x15000 needs ~", "use --columns <= ")),
    (("validate", SEED, "--shaded-columns", 20000, "--mode", "rays", "--precision", "f32"),
     ("compare --shaded 20000x15000 needs ~", "use --shaded-columns <= ")),
    (("validate", SEED, "--columns", 20000, "--mode", "rays"),
     ("compare 20000x15000 needs ~", "use --columns <= "))],
    ids=["compare-shaded", "validate-shaded", "validate"])
def test09b_shaded_and_validate_sizes_are_refused_before_allocating(cmd, said, tmp_path):
    """The shaded comparison had no memory guard: at 20000 columns it segfaulted under a
    ulimit -v (or allocated hundreds of GB); validate checks its largest comparison of each
    kind before any runs, and names the option to lower."""
    r = rtval(*cmd, *(("-o", tmp_path / "v") if cmd[0] == "validate" else ()))
    err = one_line(r, 2, *said, "available")
    assert 2 <= int(err.rsplit("<= ", 1)[1].split()[0]) < 20000
    assert not (tmp_path / "v").exists()


def test09d_validate_checks_memory_once_before_its_run(tmp_path, monkeypatch):
    """validate checks its largest comparison of each kind once, before the run; the
    comparisons in this process skip their own check (each read /proc and the cgroup's
    files: 0.1 s of a run), those on a Dask worker keep it (its memory is its own)."""
    import rt_core.memory as memory
    import tools.harness.compare as compare_mod
    import tools.harness.shaded as shaded_mod
    import tools.harness.validate as V
    calls = []
    real = memory.guard

    def counted(need, what, *a, **k):
        calls.append(what)
        return real(need, what, *a, **k)
    for mod in (memory, compare_mod, shaded_mod):
        monkeypatch.setattr(mod, "guard", counted)
    scene = parse_scene(SEED)
    rows = V.validate([scene], 16, ("f32",), ("rays", "camera"), str(tmp_path / "v"),
                      shaded_columns=8)
    assert len(rows) == 3 and calls == ["compare", "compare --shaded"], calls
    calls.clear()
    monkeypatch.setattr(V, "_on_worker", lambda: True)
    V.run_job(V.Job(scene, ("rays", "camera"), "f32", 16))
    assert calls == ["compare", "compare"], calls


def test09c_more_rays_than_a_kernel_indexes_names_a_size_that_fits():
    """Over 2^31 pixels: Dr.Jit's limit, said with the column count that fits (it gave
    none: a helper's review)."""
    r = rtval("render", SEED, "--columns", 100000, "-o", "never.exr")
    err = one_line(r, 2, "Dr.Jit indexes at most 2^31 rays in one kernel: use --columns <= ")
    fit = int(err.rsplit("<= ", 1)[1].split()[0])
    sc = parse_scene(SEED)
    assert fit * sc.default_rows(fit) < 2 ** 31 <= (fit + 2) * sc.default_rows(fit + 2)
    # rows given: the rows are named, with a count that fits ('use --columns <= 0 (and
    # --rows in proportion)' for 3 columns and 10^12 rows, a review)
    r = rtval("render", SEED, "--columns", 3, "--rows", 10 ** 12, "-o", "never.exr")
    one_line(r, 2, "use --rows <= 715827882 at 3 columns, or fewer of both")
    assert 3 * 715827882 < 2 ** 31 <= 3 * 715827883


def test10_guard_suggests_a_size_that_fits(monkeypatch):
    import rt_core.memory as memory
    monkeypatch.setattr(memory, "available", lambda: (2e9, "a test"))
    need = lambda px: render_bytes(px, "f64", True, True, 1 << 18)
    guard(need, "render", 300, 200)                       # fits: no error
    with pytest.raises(InputError, match=r"needs ~.*2\.0 GB available \(a test\)") as e:
        guard(need, "render", 20000, 15000)
    cols = int(str(e.value).rsplit("<= ", 1)[1].split()[0])
    assert need(cols * (cols * 15000 // 20000 + 1)) <= 0.9 * 2e9 < need((cols + 1) ** 2)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", ["shade_mirrors.txt", "mixed.txt",
                                  "../../shared/course-scenes/numeric/m4__v1_r04.txt"])
def test11_tiled_render_equals_one_render(precision, name):
    path = REPO / "scenes" / name
    if not path.exists():
        pytest.skip(f"{path} is not there")
    scene = parse_scene(path)
    rules = Rules.parse("screen_clip=>=,rows=shifted")     # exact decisions on the edge rows
    T = backend.types(precision, "llvm")
    cam = make_camera(scene, 97, None, "corners", rules)
    whole, rw = render_image(scene, cam, T, rules, geometry=True, shade=True)
    bands, rb = render_tiled(scene, cam, T, rules, tile_pixels=97 * 5 + 3, geometry=True,
                             shade=True)
    for k, a in whole.items():
        assert np.array_equal(a.astype(bands[k].dtype), bands[k], equal_nan=True), k
    assert (rw.bounces, rw.capped, rw.left_active) == (rb.bounces, rb.capped, rb.left_active)


def test11b_cgroup_page_cache_counts_as_available(monkeypatch):
    """Under a memory cgroup the usage includes the page cache; its inactive part is
    reclaimed on demand and must not make a render look too large."""
    import builtins
    import io
    import rt_core.memory as memory
    files = {"/sys/fs/cgroup/memory.max": "8000000000\n",
             "/sys/fs/cgroup/memory.current": "7800000000\n",
             "/sys/fs/cgroup/memory.stat": "anon 500000000\ninactive_file 7000000000\n",
             "/proc/meminfo": "MemAvailable:   100000000 kB\n"}
    real = builtins.open
    monkeypatch.setattr(builtins, "open", lambda p, *a, **k: io.StringIO(files[p])
                        if p in files else real(p, *a, **k))
    have, why = memory.available()
    assert why == "the memory cgroup's limit" and have == 8e9 - 7.8e9 + 7e9


def test12_render_under_a_memory_limit_refuses_or_fits(tmp_path):
    """Under an address-space limit, a render is refused in one line or it works: never a
    crash (it used to segfault or raise numpy's MemoryError)."""
    limit = 3 << 30
    r = rtval("render", SEED, "--columns", 10000, "--ppm", tmp_path / "a.ppm",
              "--precision", "f64", limit_as=limit)
    err = one_line(r, 2, "needs ~", "address-space limit", "use --columns <= ")
    cols = int(err.rsplit("<= ", 1)[1].split()[0])
    r = rtval("render", SEED, "--columns", cols, "--ppm", tmp_path / "a.ppm",
              "--precision", "f64", limit_as=limit, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "a.ppm").stat().st_size > cols * cols // 2


@pytest.mark.parametrize("name,precision,shade", [("shade_mirrors.txt", "f64", True),
                                                  ("mixed.txt", "f32", True),
                                                  ("mixed.txt", "f64", False)])
def test13_estimate_bounds_the_measured_peak(tmp_path, name, precision, shade):
    """The per-pixel figures are upper bounds: the real peak RSS of a render with one band
    and of one with several stays below the estimate."""
    for columns, tile in ((1000, None), (1600, 100)):
        out = ["--ppm", tmp_path / "a.ppm"] if shade else []
        args = ["render", REPO / "scenes" / name, "--columns", columns, "--rows",
                columns * 3 // 4, "--precision", precision, "-o", tmp_path / "a.exr", *out]
        if tile:
            args += ["--tile", tile]
        code = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
                "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
        r = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "tools.cli",
                            *map(str, args)], capture_output=True, text=True, cwd=REPO)
        assert r.returncode == 0, r.stderr
        peak = int(r.stdout.split()[-1]) * 1024
        pixels = columns * (columns * 3 // 4)
        band = tile * columns if tile else 1 << 21
        assert peak < render_bytes(pixels, precision, shade, True, band), (columns, peak)


# --- 6. temporaries on SIGTERM and SIGKILL ------------------------------------------------

def _start_large_render(tmp_path):
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "render",
                          str(REPO / "scenes" / "mixed.txt"), "--columns", "3000",
                          "-o", str(tmp_path / "o.exr"), "--tile", "100"],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not any(n.startswith(TMP_PREFIX) for n in os.listdir(tmp_path)):
        assert p.poll() is None and time.monotonic() - t0 < 120, "no temporary appeared"
        time.sleep(0.01)
    return p


def test14_sigterm_removes_the_temporary(tmp_path):
    p = _start_large_render(tmp_path)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM and "terminated by SIGTERM" in err, err
    assert "Traceback" not in err and os.listdir(tmp_path) == []


def test15_a_killed_runs_temporary_is_removed_by_the_next_run(tmp_path):
    p = _start_large_render(tmp_path)
    p.kill()
    p.wait()
    left = [n for n in os.listdir(tmp_path) if n.startswith(TMP_PREFIX)]
    assert left and not (tmp_path / "o.exr").exists()
    r = rtval("render", SEED, "--columns", 8, "-o", tmp_path / "small.exr")
    assert r.returncode == 0 and "removed 1 temporary file(s)" in r.stderr and left[0] in r.stderr
    assert os.listdir(tmp_path) == ["small.exr"]


@pytest.mark.parametrize("where", [["--serial"], ["--workers", "2"]], ids=["serial", "dask"])
def test15b_sigterm_during_validate_leaves_no_temporary(tmp_path, where):
    out = tmp_path / "v"
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "validate", str(SEED),
                          str(REPO / "scenes" / "mixed.txt"), "--columns", "300", "-o", str(out),
                          "--evidence", "all", *where],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    # it has written one evidence file (the seed scene's four comparisons come first)
    while not any(f.suffix == ".exr" and not f.name.startswith(".") for f in
                  (out / "exr").glob("*")) if (out / "exr").exists() else True:
        assert p.poll() is None and time.monotonic() - t0 < 120
        time.sleep(0.01)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM and "Traceback" not in err, err
    assert not [f for _, _, fs in os.walk(tmp_path) for f in fs if f.startswith(TMP_PREFIX)]
    # nor the evidence the run had finished, nor the directories it made (a robustness
    # review found dozens of EXRs in v/exr)
    assert not out.exists(), [str(p) for p in out.rglob("*")]
    # with --workers 2, the local Dask cluster's scratch directory went too
    import glob
    import tempfile
    assert not glob.glob(os.path.join(tempfile.gettempdir(), f"rtval-dask-*-{p.pid}-*"))


def test15d_a_stop_while_validate_reports_leaves_no_evidence(tmp_path, monkeypatch, capsys):
    """A Ctrl-C while validate writes its reports (after every comparison, the evidence
    finished) left the run's evidence EXRs behind, and no report to say what they were."""
    from tools import cli
    from tools.harness import validate as v
    out = tmp_path / "v"
    written = []

    def stopped(results, skipped, outdir, meta):
        written.extend(p for p in (out / "exr").glob("*.exr"))
        raise KeyboardInterrupt
    monkeypatch.setattr(v, "write_report", stopped)
    code = cli.main(["validate", str(REPO / "scenes" / "sphere.txt"), "--columns", "24",
                     "--mode", "rays", "--precision", "f32", "-o", str(out),
                     "--evidence", "all"])
    assert code == 130 and "interrupted" in capsys.readouterr().err
    assert written and not out.exists(), [str(p) for p in out.rglob("*")]


@pytest.mark.parametrize("wrapped, code", [("chained", 143), ("message", 130), ("bug", None)])
def test15c_a_signal_a_library_wrapped_is_still_the_signal(wrapped, code, monkeypatch, capsys):
    """Dr.Jit and Mitsuba re-raise an exception from the Python code they run (a custom op,
    an if_stmt's branch, a plugin's constructor) as a RuntimeError: a SIGTERM or Ctrl-C
    landing there gave a traceback and exit 1 (3 in 60 signals to a validate, a robustness
    review).  It is the signal's exit and one line; a RuntimeError of our own stays one."""
    from tools import cli
    from tools import cmd_exr
    monkeypatch.setattr(cli, "_SIGNALLED", [])

    def boom(args):
        if wrapped == "chained":
            try:
                cli._terminate(signal.SIGTERM, None)
            except cli.Terminated as t:
                raise RuntimeError("drjit.custom(): error while calling the op") from t
        if wrapped == "message":
            raise RuntimeError("loading plugin 'course_material': KeyboardInterrupt")
        raise RuntimeError("a bug")
    monkeypatch.setattr(cmd_exr, "run_info", boom)
    parser_args = ["exr", "info", "x.exr"]
    if code is None:
        with pytest.raises(RuntimeError, match="a bug"):
            cli.main(parser_args)
        return
    assert cli.main(parser_args) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0] in ("rtval: terminated by SIGTERM", "rtval: interrupted")


@pytest.mark.parametrize("first", [signal.SIGTERM, signal.SIGINT])
def test15f_a_second_signal_during_cleanup_is_noted(first, monkeypatch, capsys):
    """coreutils' timeout signals rtval and its process group: a second SIGTERM landing in
    the cleanup after the first broke it off with a traceback (a helper's review).  The
    cleanup finishes, one line, the first signal's exit; the handlers are back after."""
    from tools import cli, cmd_exr
    import rt_core.outputs as outputs
    monkeypatch.setattr(cli, "_SIGNALLED", [])
    # (a test run started in the background by a non-interactive shell inherits SIGINT
    # ignored, and Python then installs no KeyboardInterrupt for it: this test's SIGINT is
    # the interactive one)
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _second_signal(first, cli, cmd_exr, outputs, monkeypatch, capsys)
    finally:
        signal.signal(signal.SIGINT, inherited)


def _second_signal(first, cli, cmd_exr, outputs, monkeypatch, capsys):
    done = []

    def stopped(args):
        os.kill(os.getpid(), first)
        time.sleep(5)

    def cleanup():
        os.kill(os.getpid(), signal.SIGTERM)            # the second, mid-cleanup
        done.append(1)
    monkeypatch.setattr(cmd_exr, "run_info", stopped)
    monkeypatch.setattr(outputs, "cleanup", cleanup)
    before = signal.getsignal(signal.SIGINT)
    assert cli.main(["exr", "info", "x.exr"]) == 128 + first
    assert done == [1]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0] in ("rtval: terminated by SIGTERM", "rtval: interrupted")
    assert signal.getsignal(signal.SIGINT) is before


def test15h_a_killed_runs_kernel_cache_is_removed_by_the_next(tmp_path, monkeypatch):
    """rtval report and bench point Dr.Jit at an empty kernel cache of their own, removed
    at exit: a SIGKILL or the out-of-memory killer left it in the temporary directory for
    good (a review found three).  Its name holds the PID and, once rt_core is imported, it
    holds this host's and PID namespace's tag: the next run removes it; a live run's, one
    without the tag and one of another namespace stay."""
    import tempfile
    from rt_core.outputs import SPACE_MARK, _SPACE, claim_kernel_cache
    env = dict(os.environ, TMPDIR=str(tmp_path))
    env.pop("DRJIT_CACHE_DIR", None)
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "report", str(SEED), "--columns",
                          "32", "--sample", "10", "--reps", "1", "-o", str(tmp_path / "rep")],
                         cwd=REPO, env=env, start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    marked, deadline = [], time.time() + 120
    while not marked and time.time() < deadline and p.poll() is None:
        marked = list(tmp_path.glob(f"rtval-kernels-{p.pid}-*/{SPACE_MARK}"))
        time.sleep(0.02)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert marked, sorted(x.name for x in tmp_path.iterdir())
    left = marked[0].parent
    assert left.is_dir()
    dead = subprocess.Popen(["true"])
    dead.wait()
    kept = [tmp_path / f"rtval-kernels-{os.getppid()}-live",     # a live run's
            tmp_path / f"rtval-kernels-{dead.pid}-unmarked",
            tmp_path / f"rtval-kernels-{dead.pid}-elsewhere"]    # another namespace's
    for d in kept:
        d.mkdir()
    (kept[0] / SPACE_MARK).write_text(_SPACE)
    (kept[2] / SPACE_MARK).write_text("0" * len(_SPACE))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    claim_kernel_cache()
    assert not left.exists() and all(d.is_dir() for d in kept)


@pytest.mark.parametrize("at", ["remove_stale", "held"])
def test15g_a_stop_before_the_write_removes_the_directories_it_made(at, tmp_path,
                                                                     monkeypatch):
    """A signal after atomic_write made the output's directories, before the write began
    (finding stale temporaries; or held while the temporary was made, raised as the hold
    ends): the directories stayed, empty (``gallery -o DIR`` after SIGTERM, 2 of 9 tries: a
    helper's review).  Now nothing is left."""
    import contextlib
    import rt_core.outputs as outputs

    def stop(*a, **k):
        raise KeyboardInterrupt
    if at == "remove_stale":
        monkeypatch.setattr(outputs, "remove_stale", stop)
    else:
        @contextlib.contextmanager
        def held_then_raised():
            yield
            raise KeyboardInterrupt
        monkeypatch.setattr(outputs, "signals_held", held_then_raised)
    with pytest.raises(KeyboardInterrupt):
        atomic_write(str(tmp_path / "new" / "deeper" / "x.txt"),
                     lambda t: open(t, "w").write("x"))
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("where", ["file", "report"])
def test15e_sigterm_between_creating_and_registering_a_temporary(tmp_path, monkeypatch, where):
    """A SIGTERM whose handler would run right after tempfile created the temporary (before
    rtval knows its name) is held until the name is registered: the run unwinds and leaves
    nothing.  (test15b's rare leftover under Dask: the signal landed in that window.)"""
    import tempfile

    from rt_core import outputs
    from tools import cli
    from tools.harness import html_report

    real = {"mkstemp": tempfile.mkstemp, "mkdtemp": tempfile.mkdtemp}

    def late(name):
        def make(*a, **k):
            out = real[name](*a, **k)              # the file or directory exists now
            os.kill(os.getpid(), signal.SIGTERM)   # handled before make() returns
            return out
        return make

    old = signal.signal(signal.SIGTERM, cli._terminate)
    try:
        if where == "file":
            monkeypatch.setattr(tempfile, "mkstemp", late("mkstemp"))
            with pytest.raises(cli.Terminated):
                atomic_write(str(tmp_path / "out.bin"), lambda p: Path(p).write_bytes(b"x"))
        else:
            monkeypatch.setattr(tempfile, "mkdtemp", late("mkdtemp"))
            with pytest.raises(cli.Terminated):
                html_report.write_report(str(tmp_path / "rep"), "t", [], [], "cmd", {})
    finally:
        signal.signal(signal.SIGTERM, old)
        outputs.cleanup()                          # what rtval's main() does on SIGTERM
    assert sorted(os.listdir(tmp_path)) == []


def test15c_sigterm_stops_check_runs_queued_and_running(tmp_path):
    """The signal reaches rtval's main thread only; the tracer runs in a worker thread: it
    must be killed and the queued runs must not start."""
    mark = f"rtval-test-{os.getpid()}"
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "check", "--run",
                          f"sleep 30 # {mark} {{scene}} {{out}}", "--columns", "16",
                          *(str(REPO / "scenes" / n) for n in ("plane.txt", "sphere.txt",
                                                               "mixed.txt"))],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    def tracers():          # the shells running the tracer command (not rtval: its argv
        out = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
        return [ln for ln in out.splitlines()          # holds the template too)
                if mark in ln and ln.startswith(("/bin/sh -c sleep", "sh -c sleep"))]
    t0 = time.monotonic()
    while not tracers():
        assert p.poll() is None and time.monotonic() - t0 < 60
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    t1 = time.monotonic()
    p.communicate(timeout=60)
    assert p.returncode == 128 + signal.SIGTERM and time.monotonic() - t1 < 10
    time.sleep(0.3)
    assert not tracers()


def test15e_sigkill_of_check_takes_the_tracer_with_it():
    """No handler runs on SIGKILL: the tracer's process group, in a session of its own, used
    to run on after rtval (to its end, or forever for a hung one).  A watchdog shell kills
    it when rtval's end of its pipe closes; a run that ends normally leaves no watchdog."""
    mark = f"rtval-test-kill-{os.getpid()}"
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "check", "--run",
                          f"sleep 30 # {mark} {{scene}} {{out}}", "--columns", "16",
                          str(REPO / "scenes" / "plane.txt")],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def running(word):
        out = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
        return [ln for ln in out.splitlines() if word in ln and "tools.cli" not in ln]
    t0 = time.monotonic()
    while not running(mark):
        assert p.poll() is None and time.monotonic() - t0 < 60
        time.sleep(0.05)
    assert len(running("read _ ; kill -KILL")) >= 1
    p.kill()
    p.communicate(timeout=60)
    t1 = time.monotonic()
    while running(mark) and time.monotonic() - t1 < 10:
        time.sleep(0.05)
    assert not running(mark)
    # a normal run: its watchdog goes with it
    before = len(running("read _ ; kill -KILL"))
    r = rtval("check", "--run", f"true # {mark} {{scene}} {{out}}", "--columns", 16,
              REPO / "scenes" / "plane.txt")
    assert r.returncode == 1 and "wrote no image" in r.stdout + r.stderr, r.stdout + r.stderr
    assert len(running("read _ ; kill -KILL")) <= before


def test15d_another_namespaces_temporary_is_left_alone(tmp_path):
    """A PID names a process only within one host and PID namespace: a temporary of a run
    elsewhere (another container writing into a shared directory) is never removed."""
    other = tmp_path / f"{TMP_PREFIX}0123abcd-999999-x.exr"      # another tag, a dead PID
    other.write_bytes(b"x")
    assert rtval("render", SEED, "--columns", 8, "-o", tmp_path / "s.exr").returncode == 0
    assert other.exists()


def test16_a_live_runs_temporary_is_left_alone(tmp_path):
    from rt_core.outputs import _SPACE
    live = tmp_path / f"{TMP_PREFIX}{_SPACE}-{os.getpid()}-abc.exr"   # this process is alive
    live.write_bytes(b"x")
    assert rtval("render", SEED, "--columns", 8, "-o", tmp_path / "s.exr").returncode == 0
    assert live.exists()


# --- 7. inputs that are not regular files, or too large ---------------------------------------

def test17_devices_fifos_directories_and_huge_files_are_refused(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    big = tmp_path / "big.txt"
    with open(big, "wb") as f:
        f.truncate(65 << 20)                                # sparse: no disk used
    cases = [("render", "/dev/zero", "is a character device, not a scene file"),
             ("render", fifo, "is a FIFO (named pipe), not a scene file"),
             ("render", tmp_path, "is a directory; give a scene file"),
             ("render", big, "65 MiB is too large for a scene file")]
    for cmd, path, msg in cases:
        one_line(rtval(cmd, path, "--columns", 8, "-o", tmp_path / "o.exr", timeout=60), 2,
                 f"{path}: {msg}")
    one_line(rtval("exr", "info", fifo, timeout=60), 4,
             "is a FIFO (named pipe), not an EXR or other image file")  # (any format)
    one_line(rtval("check", SEED, fifo, timeout=60), 2, "is a FIFO (named pipe), not an image")
    # rtval exr takes EXRs up to the EXR limit, but another image only up to the image
    # limit (a 1.2 GB PPM was read for 14 s, then refused by OpenImageIO)
    ppm = tmp_path / "big.ppm"
    with open(ppm, "wb") as f:
        f.write(b"P6\n20000 20000\n255\n")
        f.truncate(1100 << 20)
    one_line(rtval("exr", "info", ppm, timeout=60), 4,
             f"{ppm}: 1100 MiB is too large for an image file")
    assert sorted(os.listdir(tmp_path)) == ["big.ppm", "big.txt", "fifo"]


def test04f_report_outputs_all_or_none(full_dir, tmp_path):
    """A robustness review: check's JUnit stayed when its --report hit a full disk,
    validate's report.md/json when its --junit did, stability's plot when its --json did.
    Each command's files are now written together: all of them, or none."""
    from rt_core.imageio import write_ppm
    from tools.harness.check import Renderer
    from rt_core.rules import Rules
    from rt_core.parser import parse_scene
    img = tmp_path / "ours.ppm"
    write_ppm(str(img), Renderer(parse_scene(SEED), 16, 12).image(Rules(), 1000.0))
    cases = [(("check", SEED, img, "--junit", tmp_path / "j.xml", "--report",
               full_dir / "r"), "full"),
             (("validate", SEED, "--columns", 16, "--shaded-columns", 0, "-o", tmp_path / "v",
               "--junit", "/dev/full"), "/dev/full"),
             (("stability", "--quick", "-o", tmp_path / "st", "--json", "/dev/full"),
              "/dev/full")]
    for args, where in cases:
        r = rtval(*args, timeout=300)
        err = r.stderr.strip().splitlines()
        # (validate's progress lines come first)
        assert r.returncode == 2 and "Traceback" not in r.stderr, (args, r.stderr)
        assert "cannot write: no space left on device" in err[-1], (args, err)
    assert sorted(os.listdir(tmp_path)) == ["ours.ppm"]
    assert sorted(os.listdir(full_dir)) == ["fill"]


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
def test04g_a_failing_check_stays_1_when_an_output_cannot_be_written(tmp_path):
    """check's exit 2 is bad input with no failure besides (README): a failing image whose
    --junit, or standard output, cannot be written exited 2, which a class's loop reads as
    'could not check' (a helper's review).  Now 1, with the write error's one line."""
    import numpy as np
    from rt_core.imageio import write_ppm
    black = tmp_path / "black.ppm"
    write_ppm(str(black), np.zeros((12, 16, 3), np.uint8))
    r = rtval("check", SEED, black, "--columns", 16, "--junit", "/dev/full", timeout=300)
    one_line(r, 1, "/dev/full: cannot write: no space left on device")
    assert r.stdout.startswith("FAIL"), r.stdout
    with open("/dev/full", "w") as full:
        r = subprocess.run([sys.executable, "-m", "tools.cli", "check", str(SEED), str(black),
                            "--columns", "16"], cwd=REPO, stdout=full, stderr=subprocess.PIPE,
                           text=True, timeout=300)
    one_line(r, 1, "standard output: cannot write: no space left on device")


def test04h_check_runs_share_a_small_temporary_folder(tmp_path):
    """check --run's tracer writes each image into rtval's temporary folder: each run's files
    go once read (three 147 KB images in a 400 KB TMPDIR: all pass; the third was 'the
    file is empty' while every image stayed to the end), and a run that fails there for want
    of space is rtval's error, naming the folder, not the tracer's (a helper's review)."""
    tmp = tmp_path / "t"
    tmp.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(tmp)],
                      capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (not root, or no mount permission)")
    try:
        tracer = (f"{sys.executable} -m tools.cli render {{scene}} --columns {{columns}} "
                  "--rows {rows} --precision f64 --ppm {out}")
        scenes = [SEED.with_name(n) for n in ("sphere.txt", "plane.txt", "tplane.txt")]
        env = {**os.environ, "TMPDIR": str(tmp)}

        def check():
            return subprocess.run([sys.executable, "-m", "tools.cli", "check", "--serial",
                                   "--columns", "256", "--run", tracer, *map(str, scenes)],
                                  cwd=REPO, capture_output=True, text=True, timeout=600,
                                  env=env)
        r = check()
        assert r.returncode == 0 and r.stdout.count("PASS") == 3, (r.stdout, r.stderr)
        assert os.listdir(tmp) == []
        with open(tmp / "fill", "wb") as f:         # room for a file, not for an image
            f.write(b"\0" * (340 << 10))           # (none: Python's tempfile takes /tmp)
        r = check()
        one_line(r, 2, f"{tmp}: the temporary folder is full", "set TMPDIR")
        assert os.listdir(tmp) == ["fill"]
    finally:
        subprocess.run(["umount", str(tmp)], capture_output=True)


def test04e_mitsuba_render_outputs_all_or_none(full_dir, tmp_path):
    """rtval render --mitsuba (a convert --shading scene): -o fine, --ppm on a full disk: the
    EXR is not left behind."""
    xml = tmp_path / "s.xml"
    assert rtval("convert", SEED, "--columns", 8, "--rows", 6, "--shading", "-o", xml) \
        .returncode == 0
    exr, ppm = tmp_path / "m.exr", full_dir / "m.ppm"
    r = rtval("render", "--mitsuba", xml, "-o", exr, "--ppm", ppm)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    # one line: no line announcing the EXR that was then not kept
    assert len(r.stderr.strip().splitlines()) == 1 and f"{ppm}: cannot write" in r.stderr
    assert not exr.exists() and sorted(p.name for p in full_dir.iterdir()) == ["fill"]
