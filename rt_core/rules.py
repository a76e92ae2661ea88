"""Hit rules of the course tracer and their variants seen in student implementations."""
from __future__ import annotations

from dataclasses import dataclass, asdict


@dataclass(frozen=True)
class Rules:
    """Defaults are the notes' rules; every field is a variant seen in real course code.

    t_min       plane/fplane/tplane hit needs t > t_min (notes: 0; variants 1e-4, 1e-5)
    screen_clip a plane hit in front of the window is a miss: '>' (z > 0, the notes),
                '>=' (z >= 0: a plane in z = 0 vanishes) or 'off'
    clip_spheres apply the screen clip to spheres too (some implementations do)
    edges       finite-plane bounds 'closed' (0 <= u <= w, the notes) or 'open' (0 < u < w)
    ties        exact tie in t: 'first' object in the file wins (the notes) or 'last'

    Shading and camera variants of real course programs (notes, "Variants and bugs"):

    reflect     a shaded hit divides by the 'total' path length (the notes) or by its last
                'segment' t
    rows        image row r samples course row y = H − 1 − r ('course') or H − r ('shifted':
                every row one higher, the top row above the window)
    tile_add_first  tile parity of floor((OFF + u)/w) instead of floor(OFF + u/w)
    tile_project    the tiled plane's xdir projected onto the plane (the notes) or only made
                    unit (False: u is then scaled by the cosine of xdir's tilt)
    """
    t_min: float = 0.0
    screen_clip: str = ">"
    clip_spheres: bool = False
    edges: str = "closed"
    ties: str = "first"
    reflect: str = "total"
    rows: str = "course"
    tile_add_first: bool = False
    tile_project: bool = True

    def __post_init__(self):
        checks = {"screen_clip": (">", ">=", "off"), "edges": ("closed", "open"),
                  "ties": ("first", "last"), "reflect": ("total", "segment"),
                  "rows": ("course", "shifted")}
        for name, allowed in checks.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"rules: {name} must be one of {', '.join(allowed)}, "
                                 f"not {getattr(self, name)!r}")
        if not (0.0 <= self.t_min < float("inf")):
            raise ValueError(f"rules: t_min must be a finite number >= 0, not {self.t_min!r}")

    def describe(self) -> str:
        return ",".join(f"{k}={v}" for k, v in asdict(self).items())

    @classmethod
    def parse(cls, text: str) -> "Rules":
        """'edges=open,ties=last' -> Rules(edges='open', ties='last'); 'notes': every rule
        as the notes say (Rules())."""
        if text.strip() == "notes":
            return cls()
        kw = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            key, sep, val = item.partition("=")
            if not sep or key not in cls.__dataclass_fields__:
                raise ValueError(f"rules: expected name=value with name in "
                                 f"{', '.join(cls.__dataclass_fields__)}, got {item!r}")
            if key in kw:
                raise ValueError(f"rules: {key} is given twice")
            if key == "t_min":
                try:
                    val = float(val)
                except ValueError:
                    raise ValueError(f"rules: t_min must be a number, not {val!r}") from None
            elif key in ("clip_spheres", "tile_add_first", "tile_project"):
                flag = {"1": True, "true": True, "yes": True, "on": True,
                        "0": False, "false": False, "no": False, "off": False}
                if val.lower() not in flag:
                    raise ValueError(f"rules: {key} must be true or false, not {val!r}")
                val = flag[val.lower()]
            kw[key] = val
        return cls(**kw)
