"""rt_core: an independent Dr.Jit implementation of the Clemson course ray tracer."""
from .native import native_output_captured

# Dr.Jit prints a line of its own at import when it finds an LLVM it cannot use;
# backend.require() reports that case as one clear error and passes anything else on
with native_output_captured() as DRJIT_IMPORT_MESSAGES:
    import drjit  # noqa: F401
    # Dr.Jit initializes its LLVM backend in a thread of its own from the import on, and
    # prints about an old LLVM from there: waited for inside the capture (on a loaded
    # machine that line came after it, a second line beside rtval's own one-line error)
    drjit.has_backend(drjit.JitBackend.LLVM)
# nothing else is imported here: the references import rt_core.kinds and rt_core.rules alone,
# without the tracer's scene model, parser, camera or kernels (tests/test_independence.py)
