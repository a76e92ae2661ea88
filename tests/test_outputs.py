"""rt_core.outputs: strict JSON, atomic files, figures with provenance."""
from __future__ import annotations

import json
import math

import pytest

from rt_core.outputs import WriteError, atomic_write, json_text, save_figure, write_json


def _strict(text):
    def no(c):
        raise ValueError(f"non-strict JSON constant {c}")
    return json.loads(text, parse_constant=no)


def test01_json_is_strict_with_nonfinite_values(tmp_path):
    data = {"a": float("nan"), "b": [float("inf"), -math.inf, 1.5], "c": {"d": 2}}
    assert _strict(json_text(data)) == {"a": "nan", "b": ["inf", "-inf", 1.5], "c": {"d": 2}}
    write_json(tmp_path / "x.json", data)
    assert _strict((tmp_path / "x.json").read_text())["a"] == "nan"


def test02_failed_write_leaves_nothing(tmp_path):
    def boom(tmp):
        open(tmp, "w").write("partial")
        raise RuntimeError("disk on fire")
    with pytest.raises(WriteError, match=r"out\.txt: cannot write: disk on fire") as err:
        atomic_write(tmp_path / "out.txt", boom)
    assert ".tmp" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test03_figure_carries_provenance(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    save_figure(fig, tmp_path / "f.png", {"rtval.scene": "s.txt", "rtval.precision": "f32"})
    plt.close(fig)
    info = Image.open(tmp_path / "f.png").info
    assert info["rtval.scene"] == "s.txt" and info["rtval.precision"] == "f32"


def test04_preview_png_carries_the_sources_provenance(tmp_path):
    from PIL import Image
    from tools.cli import main
    assert main(["render", "scenes/sphere.txt", "--columns", "16", "-o",
                 str(tmp_path / "s.exr")]) == 0
    assert main(["exr", "preview", str(tmp_path / "s.exr"), "-o", str(tmp_path / "p.png")]) == 0
    info = Image.open(tmp_path / "p.png").info
    assert info["rtval.scene"].endswith("sphere.txt") and info["rtval.precision"] == "f32"
    assert "depth.Z" in info["rtval.preview_of"] and "drjit=" in info["rtval.versions"]
