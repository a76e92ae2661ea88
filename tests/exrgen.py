"""EXRs rtval does not write itself, for the fault and fuzz tests: deep and multi-part."""
from __future__ import annotations

import numpy as np
import OpenEXR


def write_deep(path) -> None:
    """A 4×3 deep scanline file, channel Z: pixel (i, j) holds i + j samples."""
    deep = np.empty((3, 4), object)
    for i in range(3):
        for j in range(4):
            deep[i, j] = np.arange(i + j, dtype=np.float32)
    OpenEXR.File({"type": OpenEXR.deepscanline, "compression": OpenEXR.ZIPS_COMPRESSION},
                 {"Z": deep}).write(str(path))


def write_parts(path, parts, compression=OpenEXR.ZIP_COMPRESSION) -> None:
    """A multi-part scanline file: ``parts`` is [(part name, channel name, 2-D array)]."""
    OpenEXR.File([OpenEXR.Part({"type": OpenEXR.scanlineimage, "compression": compression},
                               {ch: np.asarray(a, np.float32)}, name=name)
                  for name, ch, a in parts]).write(str(path))
