"""The HTML report of validate, compare and check (tools/harness/html_report.py).

* the page, parsed: failures first, every image there and in its named class colours, the
  legend, evidence links that resolve, the command that reproduces a row (run, it does),
  the skipped files, provenance, nothing from the network;
* the directory is written whole or not at all (a full disk, a directory of other files);
* validate --report/--json, compare --report, check --report end to end;
* in a real headless browser (Debian's chromium + chromium-driver, driven by selenium): the
  images load, a click flips reference and ours, the legend names the classes, failures
  come first, the links resolve.  Skipped, with the reason, when no browser is installed.
"""
from __future__ import annotations

import errno
import json
import os
import re
import shlex
import shutil
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest
from PIL import Image

from tools.harness import html_report as H

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "scenes" / "sphere.txt"
MIXED = REPO / "scenes" / "mixed.txt"


class Page(HTMLParser):
    """What the tests look at: rows (status), images, links, legend items, text."""

    def __init__(self, text):
        super().__init__()
        self.rows, self.imgs, self.links, self.legend, self.external = [], [], [], [], []
        self.text, self._li = [], None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "tr" and "data-status" in a:
            self.rows.append(a["data-status"])
        if tag == "img":
            self.imgs.append(a)
        if tag == "a":
            self.links.append(a["href"])
        if tag == "li" and "data-class" in a:
            self._li = [a["data-class"], ""]
        for k in ("src", "href"):
            if k in a and "//" in a[k]:
                self.external.append(a[k])
        if tag in ("link", "iframe", "object", "embed") or (tag == "script" and "src" in a):
            self.external.append(tag)

    def handle_endtag(self, tag):
        if tag == "li" and self._li:
            self.legend.append(tuple(self._li))
            self._li = None

    def handle_data(self, data):
        self.text.append(data)
        if self._li:
            self._li[1] += data


def _pictures(seed: int, wrong: int):
    """A check-kind picture set: 12x8, ``wrong`` pixels of class wrong, one of each other."""
    rng = np.random.default_rng(seed)
    ref = rng.integers(0, 256, (8, 12, 3), dtype=np.uint8)
    ours = ref.copy()
    classes = np.zeros((8, 12), np.int64)
    classes.ravel()[1:5] = [1, 2, 3, 4]            # rounding, boundary, variant, wrong
    classes.ravel()[5:5 + wrong] = 4
    ours[classes == 4] ^= 0x80
    ours.reshape(-1, 3)[4] = ref.reshape(-1, 3)[4] ^ 1        # a wrong pixel off by one
    counts = {c: int((classes == i).sum()) for i, (c, *_) in enumerate(H.palette("check"))}
    return H.Pictures.make("check", ref, ours, classes, {"rtval.test": "yes"}), classes, counts


def _rows(tmp_path):
    ev = tmp_path / "out" / "failures" / "x.rays.f32.classes.exr"
    ev.parent.mkdir(parents=True)
    ev.write_bytes(b"not really an EXR")
    p_pass, _, c_pass = _pictures(1, 0)
    p_fail, classes, c_fail = _pictures(2, 7)
    rows = [H.Row("good.txt", "pass", "12×8: match 91", ["rules: ..."], p_pass, c_pass, [],
                  "rtval check good.txt good.ppm"),
            H.Row("crash.txt", "error", "crashed with SIGSEGV", command="rtval check crash"),
            H.Row("bad.txt", "fail", "12×8: wrong 8", ["deviation: x"], p_fail, c_fail,
                  [str(ev), str(tmp_path / "gone.exr")], "rtval check bad.txt 'bad image.ppm'")]
    skipped = [H.Skip("c/ell.txt", "unsupported", "c/ell.txt:3:1: ellipsoid is not supported")]
    return rows, skipped, classes, ev


# --- the page, parsed ----------------------------------------------------------------------------

def test01_the_page(tmp_path):
    rows, skipped, classes, ev = _rows(tmp_path)
    out = tmp_path / "rep"
    index = H.write_report(str(out), "rtval check", rows, skipped, command="rtval check ...")
    page = Page(Path(index).read_text())
    # failures first, then what could not run, then the passes
    assert page.rows == ["fail", "error", "pass"]
    # every image (and its flip side) is a PNG in the directory, the size of the comparison
    names = {im["src"] for im in page.imgs} | {im["data-b"] for im in page.imgs}
    assert len(page.imgs) == 6 and len(names) == 8
    for n in names:
        with Image.open(out / n) as im:
            assert im.format == "PNG" and im.size == (12, 8)
    # the failing row's class image: each pixel in its class's named colour
    cls = next(im["src"] for im in page.imgs if im["src"].startswith("000-") and
               im["src"].endswith(".classes.png"))
    lut = np.array([rgb for _, _, rgb, _ in H.palette("check")], np.uint8)
    assert np.array_equal(np.asarray(Image.open(out / cls).convert("RGB")), lut[classes])
    # ... and its flip side, the difference: grey >= 64 exactly where ours differs (the
    # wrong pixels), black elsewhere
    diff = np.asarray(Image.open(out / cls.replace(".classes.", ".difference.")))[..., 0]
    assert np.array_equal(diff > 0, classes == 4) and diff[classes == 4].min() >= 64
    # the legend: every class with its colour's name; the row's counts
    legend = {c: t for c, t in page.legend}
    for c, name, _, _ in H.palette("check"):
        assert c in legend and f"({name})" in " ".join(t for k, t in page.legend if k == c)
    assert ("wrong", "wrong 8") in page.legend
    # evidence: the file that exists is linked (and resolves), the missing one is not
    assert len(page.links) == 1 and (out / page.links[0]).resolve() == ev.resolve()
    text = "".join(page.text)
    assert "rtval check bad.txt 'bad image.ppm'" in text           # the command, quoted
    assert "c/ell.txt:3:1: ellipsoid is not supported" in text and "unsupported" in text
    v = H._versions()
    assert f"rtval {v['rtval']}" in text and v.get("commit", "(not a git checkout)") in text
    assert re.search(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", text)      # the date
    assert page.external == []                                      # no network
    assert "FAIL: 1 of 3 pass, 1 fail, 1 could not run; 1 skipped" in text


# --- the directory: whole or not at all ------------------------------------------------------

def _stray(parent):
    return [n for n in os.listdir(parent) if n.startswith(".tmp-rtval-")]


def test02_whole_or_not_at_all(tmp_path, monkeypatch):
    from rt_core.outputs import WriteError
    rows, skipped, _, _ = _rows(tmp_path)
    # a directory holding something else is refused, untouched
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    with pytest.raises(WriteError, match="not an rtval report.*new or empty directory"):
        H.write_report(str(other), "t", rows)
    assert os.listdir(other) == ["notes.txt"]
    # an earlier report is replaced whole
    rep = tmp_path / "rep"
    H.write_report(str(rep), "t", rows, skipped)
    H.write_report(str(rep), "t", rows[1:2])
    assert os.listdir(rep) == ["index.html"] and not _stray(tmp_path)
    # a full disk half-way: the earlier report stays as it was, no temporary is left
    H.write_report(str(rep), "t", rows[:1])
    before = {p.name: p.read_bytes() for p in rep.iterdir()}
    calls = []

    def full(path, data):
        calls.append(path)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        Path(path).write_bytes(data)
    monkeypatch.setattr(H, "_write", full)
    with pytest.raises(WriteError) as e:
        H.write_report(str(rep), "t", rows)
    assert str(e.value) == f"{rep}: cannot write: no space left on device; free some space " \
                           "or write elsewhere"
    assert {p.name: p.read_bytes() for p in rep.iterdir()} == before and not _stray(tmp_path)
    # ... and a new one in directories it would create leaves none of them
    calls.clear()
    with pytest.raises(WriteError):
        H.write_report(str(tmp_path / "a" / "b" / "rep"), "t", rows)
    assert not (tmp_path / "a").exists() and not _stray(tmp_path)
    # Ctrl-C half-way: the same
    monkeypatch.setattr(H, "_write", lambda path, data: (_ for _ in ()).throw(
        KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        H.write_report(str(tmp_path / "rep2"), "t", rows)
    assert not (tmp_path / "rep2").exists() and not _stray(tmp_path)


def test02b_a_killed_runs_temporary_is_removed(tmp_path):
    """A report directory in the making left by a run killed outright (SIGKILL) is removed
    by the next report written beside it (its process is gone)."""
    import subprocess
    import sys
    from rt_core.outputs import _SPACE, TMP_PREFIX
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    left = tmp_path / f"{TMP_PREFIX}{_SPACE}-{p.pid}-abc"
    left.mkdir()
    (left / "000-x.reference.png").write_bytes(b"half")
    alive = tmp_path / f"{TMP_PREFIX}{_SPACE}-{os.getppid()}-abc"     # a live process's
    alive.mkdir()
    H.write_report(str(tmp_path / "rep"), "t", _rows(tmp_path)[0])
    assert not left.exists() and alive.exists()


def test03_cli_refuses_a_directory_of_other_files_before_running(tmp_path, capsys,
                                                                 monkeypatch):
    import tools.harness.compare
    import tools.harness.validate
    from tools.cli import main

    def never(*a, **kw):
        raise AssertionError("compared before refusing --report")
    monkeypatch.setattr(tools.harness.compare, "compare", never)
    monkeypatch.setattr(tools.harness.validate, "compare", never)
    (tmp_path / "notes.txt").write_text("keep")
    assert main(["compare", str(SPHERE), "--columns", "8", "--report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a directory with other files in it" in err
    # a report that would replace the run's own outputs (-o inside it) is refused too
    rep = tmp_path / "new"
    assert main(["validate", str(SPHERE), "--report", str(rep), "-o", str(rep / "v")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"it holds the -o {rep / 'v'}" in err
    assert not rep.exists()


def test03b_a_report_loses_nothing_and_says_what_the_run_says(tmp_path, capsys):
    """A review in a browser: re-running into an earlier report deleted the input image put
    in it (and any note); a --junit inside the report's directory was refused or lost after
    the whole run; refused scenes gave a green PASS page while the command exited 2;
    evidence links broke on '#', '?' and '%' in names; an error row's reproduce line read
    '--columns N'; a check report without pictures labelled the tracer's column 'ours'."""
    from tools.cli import main
    rep = tmp_path / "rep"
    img = tmp_path / "a.ppm"
    img.write_bytes(b"P6 32 24 255\n" + bytes(32 * 24 * 3))
    assert main(["check", str(SPHERE), str(img), "--report", str(rep)]) == 1
    capsys.readouterr()
    shutil.copy(img, rep / "a.ppm")                 # the image put in the old report
    assert main(["check", str(SPHERE), str(rep / "a.ppm"), "--report", str(rep)]) == 2
    err = capsys.readouterr().err
    assert f"it holds the image {rep / 'a.ppm'}, which the report would replace" in err, err
    os.rename(rep / "a.ppm", rep / "notes.txt")     # a file of the user's in an old report
    assert main(["check", str(SPHERE), str(img), "--report", str(rep)]) == 2
    assert "earlier rtval report that also holds notes.txt" in capsys.readouterr().err
    assert (rep / "notes.txt").exists()
    os.remove(rep / "notes.txt")
    for command in (["check", str(SPHERE), str(img)], ["compare", str(SPHERE), "--columns", "8"],
                    ["validate", str(SPHERE), "--columns", "8", "-o", str(tmp_path / "v")]):
        new = tmp_path / f"new-{command[0]}"
        assert main(command + ["--report", str(new), "--junit", str(new / "j.xml")]) == 2
        err = capsys.readouterr().err
        assert f"it holds the --junit {new / 'j.xml'}" in err and not new.exists(), err
    # refused scenes: the page fails as the run does (exit 2); error rows keep --columns
    out = tmp_path / "refused"
    assert main(["check", "--run", "false {scene} {out}", "--columns", "16",
                 str(tmp_path / "none.txt"), str(SPHERE), "--report", str(out)]) == 1
    html = (out / "index.html").read_text()
    assert 'id="verdict">FAIL: 0 of 1 pass, 1 could not run; 1 refused<' in html, html[:2000]
    assert "--columns 16" in html and "--columns N" not in html
    assert "<th>theirs</th>" in html                # (no pictures: the column is the tracer's)
    out = tmp_path / "only-refused"
    assert main(["check", "--run", "false {scene} {out}", "--columns", "16",
                 str(tmp_path / "none.txt"), "--report", str(out)]) == 2
    assert 'id="verdict">FAIL: 0 of 0 pass; 1 refused<' in (out / "index.html").read_text()
    # evidence links percent-encoded
    odd = tmp_path / "a#1 %41?.txt"
    shutil.copy(SPHERE, odd)
    out = tmp_path / "hash"
    assert main(["validate", str(odd), "--columns", "8", "--evidence", "all", "-o",
                 str(tmp_path / "vh"), "--report", str(out)]) == 0
    links = re.findall(r'href="([^"]+\.exr)"', (out / "index.html").read_text())
    assert links and all((out / unquote(h)).resolve().is_file() for h in links), links
    assert all("#" not in h and "?" not in h for h in links)


def test03c_names_that_are_not_utf8(tmp_path, capsys):
    """A scene or student name in bytes that are not UTF-8 (Python's surrogate escapes)
    with --report gave a traceback and exit 1, a student's pass read as a failure (an
    instructor's review); validate's report.md said it could not be written.  The pages
    and the PNGs write such a byte as \\xNN, as the JUnit file does."""
    from tools.cli import main
    scene = Path(os.fsdecode(bytes(tmp_path) + b"/sph\xe9re.txt"))
    shutil.copy(SPHERE, scene)
    img = tmp_path / "a.ppm"
    assert main(["render", str(SPHERE), "--columns", "16", "--ppm", str(img)]) == 0
    rep = tmp_path / "rep"
    assert main(["check", str(scene), str(img), "--report", str(rep), "--name",
                 os.fsdecode(b"Ren\xe9")]) == 0
    html = (rep / "index.html").read_bytes().decode("utf-8")
    assert "sph\\xe9re.txt" in html and "Ren\\xe9" in html
    out = tmp_path / "v"
    assert main(["validate", str(scene), "--columns", "8", "--shaded-columns", "0", "-o",
                 str(out), "--report", str(tmp_path / "vrep")]) == 0
    assert "sph\\xe9re" in (out / "report.md").read_text()
    assert (tmp_path / "vrep" / "index.html").is_file()
    capsys.readouterr()


# --- the commands ------------------------------------------------------------------------------

def _fail_one(monkeypatch):
    """validate's rays f32 comparison of mixed.txt fails: 5 pixels marked unexplained
    (a stand-in for a real disagreement; the report only sees the comparison)."""
    import tools.harness.validate as V
    from mitsuba_ref.explain import CLASS_CODE
    real = V.compare

    def compare(scene, columns, rows, precision, mode, *a, **kw):
        cmp = real(scene, columns, rows, precision, mode, *a, **kw)
        if Path(scene.path).name == "mixed.txt" and mode == "rays":
            cmp.classes.ravel()[100:105] = CLASS_CODE["unexplained"]
            cmp.counts = {c: int((cmp.classes == i).sum()) for c, i in CLASS_CODE.items()}
        return cmp
    monkeypatch.setattr(V, "compare", compare)


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    """Real reports: validate (sphere, mixed; one comparison failing) and check (rt_core's
    image with a block of wrong pixels, and a scene rtval refuses)."""
    from tools.cli import main
    from tools.harness.check import SceneCheck, check_image
    tmp = tmp_path_factory.mktemp("reports")
    mp = pytest.MonkeyPatch()
    _fail_one(mp)
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["validate", str(SPHERE), str(MIXED), "--columns", "24", "--precision", "f32",
                   "--shaded-columns", "24", "-o", str(tmp / "v"), "--report",
                   str(tmp / "v" / "report"), "--json"])
    mp.undo()
    from tools.harness.check import Renderer
    from rt_core.parser import parse_scene
    from rt_core.rules import Rules
    theirs = Renderer(parse_scene(str(MIXED)), 24, 18).image(Rules(), 1000.0).copy()
    theirs[4:8, 4:10] = (255, 0, 255)
    res = [check_image(str(MIXED), "mine.ppm", theirs=theirs),
           check_image(str(SPHERE), "ok.ppm", theirs=Renderer(
               parse_scene(str(SPHERE)), 24, 18).image(Rules(), 1000.0)),
           SceneCheck("c/ell.txt", None, "refused", "c/ell.txt:3:1: ellipsoid is not supported")]
    H.check_report(str(tmp / "c"), res)
    return {"rc": rc, "json": out.getvalue(), "v": tmp / "v", "c": tmp / "c",
            "check_theirs": theirs}


def test04_validate_report_and_json(reports):
    assert reports["rc"] == 1
    v = reports["v"]
    data = json.loads(reports["json"])
    # --json prints what report.json holds, without the pictures
    assert data == json.loads((v / "report.json").read_text())
    assert len(data["results"]) == 6 and "pictures" not in json.dumps(data)
    page = Page((v / "report" / "index.html").read_text())
    assert page.rows == ["fail"] + ["pass"] * 5
    # the failing comparison's evidence EXRs, linked from the report, exist
    assert sorted(Path(h).name for h in page.links) == [
        f"mixed.rays.f32.{n}.exr" for n in ("classes", "diff", "mitsuba", "ours")]
    assert all((v / "report" / h).is_file() for h in page.links)
    text = "".join(page.text)
    assert "unexplained 5" in text and "classes of the shaded comparisons" in text
    for c, *_ in H.palette("geometry"):
        assert c in dict(page.legend)


def test05_a_rows_command_reproduces_it(reports, capsys):
    """The command of validate's passing shaded row, run, gives that row's classes."""
    from tools.cli import main
    data = json.loads(reports["json"])
    row = next(r for r in data["results"] if r["mode"] == "shaded" and "sphere" in r["scene"])
    cmd = H.compare_command(row)
    assert cmd in (reports["v"] / "report" / "index.html").read_text()
    words = shlex.split(cmd)
    assert words[:2] == ["rtval", "compare"]
    capsys.readouterr()
    assert main(words[1:] + ["--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["classes"] == row["classes"]


def test06_compare_report(tmp_path, capsys):
    from tools.cli import main
    rep = tmp_path / "rep"
    assert main(["compare", str(SPHERE), "--columns", "16", "--mode", "rays", "--report",
                 str(rep), "--json"]) == 0
    assert "pictures" not in capsys.readouterr().out
    page = Page((rep / "index.html").read_text())
    assert page.rows == ["pass"] and len(page.imgs) == 3
    assert all((rep / im["src"]).is_file() for im in page.imgs)
    assert (f"rtval compare {shlex.quote(str(SPHERE))} --columns 16 --mode rays --precision "
            "f32") in "".join(page.text)


def test07_check_report(reports):
    c = reports["c"]
    page = Page((c / "index.html").read_text())
    assert page.rows == ["fail", "pass"]
    text = "".join(page.text)
    assert "Skipped (1)" in text and "ellipsoid is not supported" in text
    assert "your tracer (theirs)" in text and "rtval check" in text
    # the failing row's largest wrong group magnified: the same crop of rt_core's image,
    # theirs and the classes, side by side (a single wrong pixel was hard to see)
    assert len(list(c.glob("*.png"))) == 9
    zoom, = c.glob("*.zoom.png")
    from PIL import Image
    z = np.asarray(Image.open(zoom).convert("RGB"))
    theirs = reports["check_theirs"]
    k = 120 // 12                            # rows 4-7, columns 4-9, 3 around: 10 x 12
    assert z.shape == (10 * k, 3 * 12 * k + 2 * 4, 3), z.shape
    crop = np.repeat(np.repeat(theirs[1:11, 1:13], k, 0), k, 1)
    assert (z[:, 12 * k + 4:24 * k + 4] == crop).all()
    html = (c / "index.html").read_text()
    assert f'src="{zoom.name}"' in html and "rows 1–10, columns 1–12, magnified 10×" in html
    # under the tracer's image, not in the text (a review: it pushed the table apart)
    cell = re.search(r'<td class="ours">(.*?)</td>', html).group(1)
    assert f'src="{zoom.name}"' in cell, cell
    assert 'alt="your tracer (theirs) of mixed.txt (mine.ppm)"' in html, html


# --- in a real browser ---------------------------------------------------------------------------

def _browser():
    """A headless Chromium driven by selenium, or pytest.skip with the reason."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[test]')")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("no headless browser: install Debian's chromium and chromium-driver "
                    "(tools/in-env.sh python -m pytest does)")
    opts = webdriver.ChromeOptions()
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=1400,2000", "--allow-file-access-from-files"):
        opts.add_argument(a)
    opts.binary_location = chromium
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=Service(driver))


@pytest.fixture(scope="module")
def browser():
    d = _browser()
    yield d
    d.quit()


def _file(url: str) -> Path:
    u = urlparse(url)
    assert u.scheme == "file", url
    return Path(unquote(u.path))


LOADED = "return [...document.images].map(i => [i.complete, i.naturalWidth, i.naturalHeight])"


@pytest.mark.parametrize("which", ["v", "c"])
def test08_in_a_browser(reports, browser, which):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait
    index = reports[which] / ("report" if which == "v" else "") / "index.html"
    browser.get(index.resolve().as_uri())
    # every image loaded, at its size
    WebDriverWait(browser, 10).until(lambda d: all(c for c, _, _ in d.execute_script(LOADED)))
    sizes = browser.execute_script(LOADED)
    assert sizes and all(w > 0 and h > 0 for _, w, h in sizes), sizes
    # failures first
    rows = browser.find_elements(By.CSS_SELECTOR, "#results tbody tr")
    statuses = [r.get_attribute("data-status") for r in rows]
    assert statuses[0] == "fail" and statuses == sorted(statuses, key=H.STATUS_ORDER.get)
    # a click flips the reference slot to ours and back; the caption follows; Enter too
    img = rows[0].find_element(By.CSS_SELECTOR, "td.reference img")
    a, b = img.get_attribute("data-a"), img.get_attribute("data-b")
    assert img.get_attribute("src").endswith(a)
    img.click()
    assert img.get_attribute("src").endswith(b) and "ours" in b
    WebDriverWait(browser, 5).until(lambda d: d.execute_script(
        "return arguments[0].complete && arguments[0].naturalWidth > 0", img))
    cap = rows[0].find_element(By.CSS_SELECTOR, "td.reference figcaption").text
    assert cap.startswith(img.get_attribute("data-b-label"))
    img.send_keys(Keys.ENTER)
    assert img.get_attribute("src").endswith(a)
    cls = rows[0].find_element(By.CSS_SELECTOR, "td.classes img")
    cls.click()
    assert cls.get_attribute("src").endswith(".difference.png")
    # the legend names every class of the page's kind
    kind = "geometry" if which == "v" else "check"
    legend = browser.find_element(By.CSS_SELECTOR, "#legends").text
    for c, name, _, _ in H.palette(kind):
        assert f"{c} ({name})" in legend
    # every link resolves to a file that exists
    for link in browser.find_elements(By.CSS_SELECTOR, "a[href]"):
        assert _file(link.get_property("href")).is_file()
    # "show only what did not pass" hides the passing rows
    browser.find_element(By.ID, "failures-only").click()
    shown = [r.get_attribute("data-status") for r in rows if r.is_displayed()]
    assert shown and set(shown) == {"fail"}
    # and the page's script raised nothing
    assert [e for e in browser.get_log("browser") if e["level"] == "SEVERE"] == []


# Machado, Oliveira and Fernandes (2009), severity 1.0, on linear RGB
DICHROMACY = {
    "deuteranopia": [[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                     [-0.011820, 0.042940, 0.968881]],
    "protanopia": [[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216],
                   [-0.003882, -0.048116, 1.051998]],
    "tritanopia": [[1.255528, -0.076749, -0.178779], [-0.078411, 0.930809, 0.147602],
                   [0.004733, 0.691367, 0.303900]]}


def _seen(rgb, m):
    c = np.asarray(rgb, float) / 255
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    out = np.clip(np.asarray(m) @ lin, 0, 1)
    return 255 * np.where(out <= 0.0031308, 12.92 * out, 1.055 * out ** (1 / 2.4) - 0.055)


@pytest.mark.parametrize("kind", ["check", "shaded"])
def test09_the_course_image_classes_are_told_apart_by_the_colour_blind(kind):
    """The classes of a check (and of a shaded comparison) stay 100 apart in sRGB under each
    simulated dichromacy: the old palette's green variant and red wrong came to 77 for a
    deuteranope, its red wrong and dark grey match to 72 for a protanope."""
    import itertools
    colours = [rgb for _, _, rgb, _ in H.palette(kind)]
    for name, m in DICHROMACY.items():
        for a, b in itertools.combinations(colours, 2):
            assert np.linalg.norm(_seen(a, m) - _seen(b, m)) >= 100, (name, a, b)


def test10_the_magnified_view_of_a_group_at_a_border_or_too_large():
    """A group in the image's corner: the crop moved inside the image, its size kept; a group
    larger than ZOOM_MAX (a whole wrong image, a long thin strip): a ZOOM_MAX square around
    its middle pixel, said to be part of it, never 'magnified 1×'."""
    from tools.harness.check import worst_region
    H_, W_ = 60, 80
    imgs = [np.random.default_rng(k).integers(0, 256, (H_, W_, 3), np.uint8) for k in range(3)]
    for rows, cols in (([0, 0], [0, 0]), ([59, 59], [79, 79]), ([10, 12], [5, 79]),
                       ([0, 59], [0, 79])):
        wrong = np.zeros((H_, W_), bool)
        wrong[rows[0]:rows[1] + 1, cols[0]:cols[1] + 1] = True
        worst = worst_region(wrong)
        assert (worst["rows"], worst["columns"]) == (rows, cols)
        img, k, (y0, y1, x0, x1), part = H.zoom_picture(imgs, worst)
        assert k >= 4 and part == (max(rows[1] - rows[0], cols[1] - cols[0]) + 7 > H.ZOOM_MAX)
        assert 0 <= y0 <= y1 < H_ and 0 <= x0 <= x1 < W_
        # the whole group in the crop, or (part of it) a square around its middle
        middle = lambda a, b, n: min(max((a + b) / 2, H.ZOOM_MAX / 2 - 0.5),
                                     n - H.ZOOM_MAX / 2 - 0.5)
        assert (y0 <= rows[0] and rows[1] <= y1 and x0 <= cols[0] and cols[1] <= x1) if \
            not part else wrong[y0:y1 + 1, x0:x1 + 1].any() and \
            abs((y0 + y1) / 2 - middle(*rows, H_)) <= 1 and \
            abs((x0 + x1) / 2 - middle(*cols, W_)) <= 1
        h, w = y1 - y0 + 1, x1 - x0 + 1
        assert (h, w) == ((H.ZOOM_MAX,) * 2 if part else (7, 7)) and \
            img.shape == (h * k, 3 * w * k + 8, 3)
        assert (img[:, w * k + 4:2 * w * k + 4] ==
                np.repeat(np.repeat(imgs[1][y0:y1 + 1, x0:x1 + 1], k, 0), k, 1)).all()
    # a large L-shaped group with a lone wrong pixel in its box's corner (a review: the crop
    # went around the lone pixel, and showed nothing of the group it named)
    m = np.zeros((200, 200), bool)
    m[0:101, 100] = m[100, 0:101] = m[0, 0] = True
    big = [np.zeros((200, 200, 3), np.uint8)] * 3
    _, k, (y0, y1, x0, x1), part = H.zoom_picture(big, worst_region(m))
    crop = m[y0:y1 + 1, x0:x1 + 1]
    assert part and not crop[0, 0] and crop.sum() >= H.ZOOM_MAX, ((y0, y1, x0, x1), crop.sum())
