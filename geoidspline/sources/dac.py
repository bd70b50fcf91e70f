"""NGA's ``WW15MGH.DAC``: the EGM96 15' grid as big-endian int16 centimetres.

The file has no header and no no-data value (NGA's grid is global and complete): it is
recognised by its exact size, 721 x 1440 x 2 bytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputFileError
from .files import finish_grid, provenance_of
from .grid import GeoidGrid

# NGA's WW15MGH.DAC: 15' EGM96 grid, 90N->90S by 0E->359.75E, int16 big-endian cm.
_DAC_ROWS, _DAC_COLS, _DAC_STEP = 721, 1440, 0.25


DAC_BYTES = _DAC_ROWS * _DAC_COLS * 2


def looks_like_dac(head: bytes, size: int) -> bool:
    """Whether a file has the size of NGA's WW15MGH.DAC (its only signature)."""
    return size == DAC_BYTES


def check_dac_size(path, head: bytes, size: int) -> None:
    """Refuse a file whose size is not WW15MGH.DAC's, before reading it."""
    if size != DAC_BYTES:
        raise InputFileError(
            path,
            f"DAC file is {size} bytes, but {_DAC_ROWS} x {_DAC_COLS} int16 nodes "
            f"(NGA WW15MGH.DAC, 15' EGM96) need {DAC_BYTES}",
        )


# -- NGA WW15MGH.DAC -------------------------------------------------------------------
def read_dac(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    check_dac_size(path, data[:0], len(data))
    cm = np.frombuffer(data, ">i2").reshape(_DAC_ROWS, _DAC_COLS)
    values = cm[::-1].astype(np.float64) / 100.0  # rows 90N->90S, centimetres
    lat = -90.0 + _DAC_STEP * np.arange(_DAC_ROWS)
    lon = _DAC_STEP * np.arange(_DAC_COLS)
    prov = provenance_of(path, sha256, notes=("NGA binary grid, int16 centimetres",))
    return finish_grid(path, lat, lon, values, prov, complete=complete)
