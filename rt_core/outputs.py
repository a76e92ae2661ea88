"""Writing outputs: atomically (temporary name, then rename), strict JSON, figures.

Every file rtval writes goes through ``atomic_write``, so a failed or interrupted run never
leaves a partial file behind.
"""
from __future__ import annotations

import errno
import json
import math
import os
import stat
import tempfile
from pathlib import Path


def atomic_write(path: str, write) -> None:
    """Call ``write(tmp_path)`` and rename the result to ``path`` only if it succeeded.

    A symlink is written through (its target is replaced); an existing non-regular file
    (``/dev/null``, a pipe) is written directly, since it cannot be replaced; the new file
    gets the mode of the file it replaces, or 0666 less the umask."""
    path = os.path.realpath(os.fspath(path))
    if os.path.isdir(path):
        raise IsADirectoryError(errno.EISDIR, "is a directory, expected a file name", path)
    if os.path.exists(path) and not os.path.isfile(path):
        write(path)
        return
    directory = os.path.dirname(path)
    try:
        os.makedirs(directory, exist_ok=True)
    except FileExistsError:
        raise NotADirectoryError(errno.ENOTDIR, "not a directory", directory) from None
    if os.path.exists(path):
        mode = stat.S_IMODE(os.stat(path).st_mode)
    else:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=directory)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def jsonable(x):
    """NaN and ±Inf become the strings "nan", "inf", "-inf", so that JSON stays strict."""
    if isinstance(x, float) and not math.isfinite(x):
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    return x


def json_text(data, indent: int = 1) -> str:
    return json.dumps(jsonable(data), indent=indent, allow_nan=False) + "\n"


def write_json(path: str, data, indent: int = 1) -> None:
    text = json_text(data, indent)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def save_figure(fig, path: str, provenance: dict | None = None, **kw) -> None:
    """A matplotlib figure as PNG, atomically, with provenance in its text chunks."""
    meta = {k: str(v) for k, v in (provenance or {}).items()}
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", metadata=meta, **kw))
