"""InputError alone, so that the references can raise it without importing the tracer."""


class InputError(Exception):
    """A bad option value or a missing input file; ``str(err)`` is one line."""
    exit_code = 2
