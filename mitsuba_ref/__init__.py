"""The references that rt_core is checked against, sharing no code with it (tests/test_independence.py):

* ``scenefile``: the course scene format's numbers as written, read on their own;
* ``oracle``: a float64 per-ray tracer written straight from the notes, with error bounds;
* ``exact``: the exact rational oracle (hit rules decided without rounding);
* ``explain``: the classification of disagreeing pixels and rays;
* ``convert`` and ``reference``: the equivalent Mitsuba 3 scene and its renders.
"""
