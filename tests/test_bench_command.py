"""rtval bench --command: a smoke run (CI); the figures themselves come from real runs."""
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
        {"geometry", "shaded"}
    for c in res["cases"]:
        p = c["phases"]
        assert c["columns"] == 48 and c["runs"] == 1
        parts = sum(p[k]["median"] for k in ("import", "parse", "kernel", "write"))
        assert abs(parts - p["wall"]["median"]) < 1e-6 and all(
            p[k]["median"] > 0 for k in ("import", "kernel", "write"))
        assert c["largest"] in ("import", "parse", "kernel", "write")
    assert "largest" in r.stdout and "kernel" in r.stdout
