"""NVIDIA FLIP (the ``flip-evaluator`` wheel): the perceptual error map of two colour images,
and that map as a picture in the magma colour map FLIP's own tool draws it in."""
from __future__ import annotations

import numpy as np


def flip_map(ref: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, float, dict]:
    """FLIP of two (rows, columns, 3) colour images: (per-pixel error in [0, 1], its mean,
    FLIP's parameters with ``dynamic_range``).  LDR (sRGB-encoded values in [0, 1], as PPM,
    PNG and the course programs' colours are) when both images lie within [0, 1], else HDR
    (linear values >= 0, judged over FLIP's range of exposures).  The values must be
    finite (the caller says which are not)."""
    import flip_evaluator
    ref = np.ascontiguousarray(ref, np.float32)
    test = np.ascontiguousarray(test, np.float32)
    ldr = ref.min() >= 0 and test.min() >= 0 and ref.max() <= 1 and test.max() <= 1
    err, mean, params = flip_evaluator.evaluate(ref, test, "LDR" if ldr else "HDR",
                                                applyMagma=False)
    params = {k: (float(v) if isinstance(v, float) else v) for k, v in params.items()}
    params["dynamic_range"] = "LDR" if ldr else "HDR"
    return np.asarray(err, np.float32).reshape(ref.shape[:2]), float(mean), params


def flip_colours(err: np.ndarray) -> np.ndarray:
    """A FLIP error map in magma: (rows, columns, 3) uint8, 0 black, 1 light yellow."""
    import matplotlib
    rgb = matplotlib.colormaps["magma"](np.clip(err, 0.0, 1.0))[..., :3]
    return (rgb * 255 + 0.5).astype(np.uint8)
