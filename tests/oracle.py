"""The per-ray float64 oracle: moved to mitsuba_ref/oracle.py (``rtval report`` measures errors
against it); this module re-exports it for the tests."""
from mitsuba_ref.oracle import *  # noqa: F401,F403
