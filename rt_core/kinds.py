"""The one table of shape kinds.  Every per-kind dispatch (rt_core's kernels, the references'
oracles, the Mitsuba converter, the readers) is keyed by these names, and a kind missing from a
dispatch raises instead of falling through to another kind (tests/test_kinds.py checks that
every table covers every kind).

A pure table: no geometry, nothing the references could share with the tracer's arithmetic.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kind:
    name: str                # keyword of the keyword dialect
    code: int                # numeric dialect's object code
    bounded: bool            # has a finite extent (a bounding box)
    planar: bool             # the plane equation n·(x − point) = 0 with a frame or not


KINDS = {
    "sphere": Kind("sphere", 13, True, False),
    "plane": Kind("plane", 14, False, True),
    "fplane": Kind("fplane", 15, True, True),
    "tplane": Kind("tplane", 16, False, True),
}
LIGHTS = {"pointlight": 10}
KEYWORDS = tuple(KINDS) + tuple(LIGHTS)
CODES = {**{k.code: n for n, k in KINDS.items()}, **{c: n for n, c in LIGHTS.items()}}
PLANE_KINDS = tuple(n for n, k in KINDS.items() if k.planar)
KIND_CODE = {n: i for i, n in enumerate(KINDS)}      # kernels' kind number


def kind(name: str) -> Kind:
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"unknown object kind {name!r} (known: {', '.join(KINDS)})") from None


def dispatch(table: dict, name: str):
    """``table[name]`` for a per-kind table; an unknown kind raises (no fall-through)."""
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"object kind {name!r} has no entry here (known: "
                         f"{', '.join(sorted(table))})") from None


def kind_of_keyword(word: str) -> str:
    w = word.lower()
    if w not in KEYWORDS:
        raise ValueError(f"unknown object keyword {word!r}")
    return w


def kind_of_code(code: int) -> str:
    if code not in CODES:
        raise ValueError(f"unknown object code {code}")
    return CODES[code]
