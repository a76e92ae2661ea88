"""The tests' one tolerance table: the precisions every precision-parametrized test runs, their
unit roundoffs, and the bounds rt_core's outputs are held to against the float64 oracle
(geometry, ``GEOMETRY``) and in shaded images (``SHADED``).  A tolerance is changed here, once,
with the measurement that justifies it."""
from __future__ import annotations

from dataclasses import dataclass

PRECISIONS = ("f32", "f64")
U = {"f32": 2.0 ** -24, "f64": 2.0 ** -53}          # unit roundoff


@dataclass(frozen=True)
class Tol:
    u: float            # unit roundoff of the precision
    flag: float         # a decision whose oracle margin is below this may flip: pixel excused
    value: float        # |ours - oracle| <= value * (err + |oracle|) for every output value
    excused: float      # at most this fraction of the pixels may be excused


# The oracle carries, for every value, a first-order worst-case bound `err` on its rounding
# error in units of the unit roundoff u (Wilkinson's running error bound of the notes' own
# formulas, every operation rounded once; tests/oracle.py), and for every hit/miss decision a
# margin = |distance from the threshold| / (that quantity's bound).  Measured on the 12 random
# scenes and scenes/*.txt, the tracer's error never exceeded 1.3 * u * err in either precision
# (its formulas differ: viewpoint-relative, division-free u/v, stable sphere discriminant).
#
# value = 4:    4x the bound, 3x above the worst seen; "+ |oracle|" is the one rounding every
#               implementation spends on the result, so a value the notes' formula gets exactly
#               is still allowed the tracer's last rounding.  f64 depth is therefore held to
#               ~4e-15..4e-13 relative (the brief's 1e-9 is implied); f32 depth to
#               4 * 2^-24 * (err_t/t + 1), typically (10..100) * 2.4e-7 = 2.4e-6..2.4e-5
#               relative, larger only where t is ill-conditioned (grazing planes).
# flag = 64 u:  a decision flips only if the tracer's error in the decided quantity exceeds
#               its distance from the threshold; 64x the bound leaves 50x headroom over the
#               worst ratio seen.  64 * 2^-24 = 3.8e-6 (f32), 64 * 2^-53 = 7.1e-15 (f64).
#               Since margins are relative to the quantity's own error bound, a flagged f32
#               edge pixel lies within ~1e-5 of a pixel width of the edge: almost none do.
# excused = 1%: measured at most 13 of 3072 pixels (0.4%) in f32 and none in f64.
GEOMETRY = {p: Tol(u=U[p], flag=64 * U[p], value=4.0, excused=0.01) for p in PRECISIONS}
# Shaded images against the shading oracle: flagged fractions measured at 40 columns over
# scenes/*.txt, at most 3.9% (mixed.txt) in f32, none in f64.  (The oracle's bounds are
# worst-case sums over every operation, so an f32 flag covers far more than the pixels that
# actually flip: 1 of 12000 did.)
SHADED = {"f32": 0.05, "f64": 0.005}
