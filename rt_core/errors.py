"""The errors a user can cause; the CLI prints them as one line and exits non-zero."""
from .scene import SceneError, GeometryError
from .exrio import ExrError
from .backend import BackendError
from .imageio import ImageError
from .usererror import InputError


# OSError: a missing input, an output path under a file, a full disk, ... (one line each)
USER_ERRORS = (SceneError, GeometryError, ExrError, BackendError, InputError, ImageError,
               OSError)
