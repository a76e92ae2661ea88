"""Compare the C course tracer (tests/ctracer/course.c) with rt_core, scene by scene.

    .venv/bin/python tests/ctracer/compare_rtcore.py BINARY COLUMNS SCENE... \
        [--rules RULES] [--max-dist D] [--oracle]

For each scene: the C tracer's hit dump and PPM against ``rtval render --precision f64``
(EXR object.id and depth.Z, and its --ppm with the same --max-dist).  Prints per scene the
count of pixels whose primary object id differs, the largest relative depth difference where
the ids agree (the EXR stores float32, so ~6e-8 is agreement), the count of PPM pixels that
differ and the largest channel difference.  With --oracle also the PPM against the float64
per-pixel shading oracle (tests/shade_oracle.py), with how many differing pixels the oracle
does not flag as near a decision boundary (slow: minutes on mirror scenes).

BINARY must be compiled with -DMAX_DIST equal to --max-dist (course defaults to 50000).
Not a pytest module (no test_ prefix): a tool for people.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)


def read_ppm(path: str) -> np.ndarray:
    data = open(path, "rb").read()
    m = re.match(rb"P6\s+(\d+)\s+(\d+)\s+255\s", data)
    if not m:
        raise ValueError(f"{path}: not a binary P6 PPM with maxval 255")
    w, h = int(m.group(1)), int(m.group(2))
    body = data[m.end():]
    if len(body) != w * h * 3:
        raise ValueError(f"{path}: {len(body)} bytes of pixels, expected {w * h * 3}")
    return np.frombuffer(body, np.uint8).reshape(h, w, 3)


def run_c(binary: str, scene: str, cols: int, tmp: str):
    """(image, ids, t) from the C tracer, or an error string."""
    hits, ppm = os.path.join(tmp, "c.hits"), os.path.join(tmp, "c.ppm")
    with open(scene, "rb") as f, open(ppm, "wb") as o:
        r = subprocess.run([binary, str(cols), "--hits", hits], stdin=f, stdout=o,
                           stderr=subprocess.PIPE)
    if r.returncode:
        return f"C exit {r.returncode}: {r.stderr.decode().strip()}"
    img = read_ppm(ppm)
    h, w = img.shape[:2]
    a = np.loadtxt(hits, dtype=np.float64, ndmin=2)
    assert a.shape == (w * h, 4), a.shape
    assert (a[:, 0].reshape(h, w) == np.arange(w)[None, :]).all(), "columns out of order"
    assert (a[:, 1].reshape(h, w) == np.arange(h)[:, None]).all(), "rows out of order"
    return img, a[:, 2].astype(np.int64).reshape(h, w), a[:, 3].reshape(h, w)


def run_rt(scene: str, cols: int, rules, max_dist: float, tmp: str):
    from rt_core.exrio import read_exr
    exr, ppm = os.path.join(tmp, "r.exr"), os.path.join(tmp, "r.ppm")
    rtval = os.path.join(os.path.dirname(sys.executable), "rtval")
    cmd = [rtval, "render", scene, "--columns", str(cols), "--precision", "f64", "-o", exr,
           "--ppm", ppm, "--max-dist", repr(max_dist)]
    if rules:
        cmd += ["--rules", rules]
    r = subprocess.run(cmd, capture_output=True)
    if r.returncode:
        return f"rtval exit {r.returncode}: {r.stderr.decode().strip().splitlines()[-1]}"
    ch, _ = read_exr(exr)
    return read_ppm(ppm), ch["object.id"].astype(np.int64), ch["depth.Z"].astype(np.float64)


def oracle_diff(scene: str, cols: int, rows: int, rules, max_dist: float, img) -> str:
    from rt_core.parser import parse_scene
    from rt_core.rules import Rules
    from tests import shade_oracle as so
    orc = so.render_shade_oracle(parse_scene(scene), cols, rows,
                                 rules=Rules.parse(rules) if rules else Rules(),
                                 max_dist=max_dist)
    fl = so.flags(orc, "f64")
    diff = np.any(img != so.quantize(orc["I"]), -1)
    return f"oracle: {int(diff.sum())} px differ, {int((diff & ~fl['any']).sum())} unflagged"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("columns", type=int)
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--rules", default=None, help="rtval --rules for rt_core and the oracle")
    ap.add_argument("--max-dist", type=float, default=50000.0)
    ap.add_argument("--oracle", action="store_true")
    args = ap.parse_args()
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        for s in args.scenes:
            name = os.path.basename(s)
            c = run_c(args.binary, s, args.columns, tmp)
            r = run_rt(s, args.columns, args.rules, args.max_dist, tmp)
            if isinstance(c, str) or isinstance(r, str):
                both = isinstance(c, str) and isinstance(r, str)
                print(f"{name}: {'both refuse' if both else 'MISMATCH'}: "
                      f"{c if isinstance(c, str) else 'C ok'} | "
                      f"{r if isinstance(r, str) else 'rtval ok'}")
                bad += not both
                continue
            cimg, cid, ct = c
            rimg, rid, rz = r
            if cimg.shape != rimg.shape:
                print(f"{name}: MISMATCH size {cimg.shape} vs {rimg.shape}")
                bad += 1
                continue
            same = (cid == rid) & (cid >= 0)
            rel = np.abs(ct[same] - rz[same]) / np.abs(rz[same])
            pd = np.any(cimg != rimg, -1)
            line = (f"{name}: {cimg.shape[1]}x{cimg.shape[0]} id-diff {int((cid != rid).sum())}"
                    f"  depth-rel-max {rel.max() if rel.size else 0:.2g}"
                    f"  ppm-diff {int(pd.sum())} (max {int(np.abs(cimg.astype(int) - rimg).max())})")
            if args.oracle:
                line += "  " + oracle_diff(s, args.columns, cimg.shape[0], args.rules,
                                           args.max_dist, cimg)
            print(line, flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
