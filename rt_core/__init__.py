"""rt_core: an independent Dr.Jit implementation of the Clemson course ray tracer."""
from .scene import (Scene, SceneError, Material, PointLight, Sphere, Plane, FPlane, TPlane,
                    KINDS)
from .rules import Rules

__all__ = ["Scene", "SceneError", "Material", "PointLight", "Sphere", "Plane", "FPlane",
           "TPlane", "KINDS", "Rules"]
