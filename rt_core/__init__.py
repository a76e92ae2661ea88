"""rt_core: an independent Dr.Jit implementation of the Clemson course ray tracer."""
from .native import native_output_captured

# Dr.Jit prints a line of its own at import when it finds an LLVM it cannot use;
# backend.require() reports that case as one clear error and passes anything else on
with native_output_captured() as DRJIT_IMPORT_MESSAGES:
    import drjit  # noqa: F401
from .scene import (Scene, SceneError, Material, PointLight, Sphere, Plane, FPlane, TPlane,
                    KINDS)
from .rules import Rules

__all__ = ["Scene", "SceneError", "Material", "PointLight", "Sphere", "Plane", "FPlane",
           "TPlane", "KINDS", "Rules"]
