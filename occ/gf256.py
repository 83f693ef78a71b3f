"""GF(256) as ``reedsolo`` defines it (primitive polynomial 0x11d, generator 2): its exponent and
logarithm tables as arrays, and the full multiplication table. Shared by the batched encoder
(``eventocc.occ.fec``) and the compiled corrector (``eventocc.occ.rs_kernel``)."""

from __future__ import annotations

import numpy as np
import reedsolo

reedsolo.init_tables()  # the defaults every RSCodec uses; idempotent
GF_EXP = np.array(reedsolo.gf_exp[:512], dtype=np.int64)
GF_LOG = np.array(reedsolo.gf_log[:256], dtype=np.int64)


def _gf_mul_table() -> np.ndarray:
    table = GF_EXP[GF_LOG[:, None] + GF_LOG[None, :]].astype(np.uint8)
    table[0, :] = table[:, 0] = 0
    return table


GF_MUL = _gf_mul_table()
"""(256, 256) uint8: ``GF_MUL[a, b]`` is the GF(256) product of a and b."""
