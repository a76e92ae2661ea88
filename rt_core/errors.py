"""The errors a user can cause; the CLI prints them as one line and exits non-zero."""
from .scene import SceneError, GeometryError
from .exrio import ExrError
from .backend import BackendError


class InputError(Exception):
    """A bad option value or a missing input file; ``str(err)`` is one line."""
    exit_code = 2


USER_ERRORS = (SceneError, GeometryError, ExrError, BackendError, InputError,
               FileNotFoundError, IsADirectoryError, PermissionError)
