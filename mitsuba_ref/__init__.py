"""The references that rt_core is checked against, sharing no code with it (tests/test_independence.py):

* ``scenefile``: the course scene format's numbers as written, read on their own;
* ``oracle``: a float64 per-ray tracer written straight from the notes, with error bounds;
* ``exact``: the exact rational oracle (hit rules decided without rounding);
* ``explain``: the classification of disagreeing pixels and rays;
* ``convert`` and ``reference``: the equivalent Mitsuba 3 scene and its renders.
"""

import sys as _sys


def _register_if_loaded() -> None:
    """The course plugins (``integrator``) are registered whenever mitsuba_ref loads Mitsuba
    (``convert.mitsuba()``); when Mitsuba is already imported in rtval's variant, right away,
    so that ``mi.load_file`` reads a ``rtval convert --shading`` scene after
    ``import mitsuba_ref``.  (Importing mitsuba_ref never imports Mitsuba itself.)"""
    mi = _sys.modules.get("mitsuba")
    if mi is None or not hasattr(mi, "variant"):
        return
    from .convert import VARIANT
    if mi.variant() == VARIANT:
        from .integrator import register
        register(mi)


_register_if_loaded()
