"""The per-ray float64 oracle: moved to rt_core/oracle.py (``rtval report`` measures errors
against it); this module re-exports it for the tests."""
from rt_core.oracle import *  # noqa: F401,F403
