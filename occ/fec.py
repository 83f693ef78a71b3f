"""Reed-Solomon over GF(256), as ``reedsolo`` defines it (primitive polynomial 0x11d, generator 2,
first consecutive root 0), with fast paths.

``reedsolo`` is pure Python (its compiled ``creedsolo`` is not in the wheel), so encoding a frame
with it costs milliseconds. RS encoding and the syndromes are linear maps over GF(256), so we
derive their matrices once from ``reedsolo`` itself and apply them to whole batches of codewords
with table look-ups. Only codewords whose syndromes are non-zero (or that carry erasures) go to
the corrector, ``eventocc.occ.rs_kernel`` (reedsolo's algorithm compiled with numba), which is
loaded only then: the server, which only encodes, runs without numba (about 100 MiB less resident
memory).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import reedsolo

from eventocc.occ.gf256 import GF_EXP, GF_MUL

MAX_CODEWORD = 255


def _gf_matmul(rows: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """(m, a) x (a, b) -> (m, b) over GF(256): products by look-up, sums by XOR."""
    return np.bitwise_xor.reduce(GF_MUL[rows[:, :, None], matrix[None, :, :]], axis=1)


@cache
def _parity_matrix(k: int, nsym: int) -> np.ndarray:
    """(k, nsym): row i is the parity of the unit message e_i, i.e. x^(nsym + k-1-i) mod g(x)
    for reedsolo's generator polynomial g (encoding is linear)."""
    g = np.array(reedsolo.rs_generator_poly(nsym), dtype=np.uint8)  # monic, highest first
    out = np.zeros((k, nsym), dtype=np.uint8)
    row = g[1:].copy()  # x^nsym mod g
    for i in range(k - 1, -1, -1):
        out[i] = row
        row = np.append(row[1:], 0) ^ GF_MUL[row[0], g[1:]]  # times x, reduced mod g
    return out


@cache
def _syndrome_matrix(n: int, nsym: int) -> np.ndarray:
    """(n, nsym): syndrome j of a codeword is its polynomial at alpha^j, so byte i (the
    coefficient of x^(n-1-i)) contributes with weight alpha^(j (n-1-i))."""
    powers = np.outer(np.arange(n - 1, -1, -1), np.arange(nsym)) % 255
    return GF_EXP[powers].astype(np.uint8)


@dataclass(frozen=True)
class ReedSolomon:
    """A (possibly shortened) RS(n, k) code: ``k`` data bytes then ``n - k`` parity bytes.

    It corrects ``e`` errors and ``f`` erasures whenever ``2 e + f <= n - k``.
    """

    n: int
    k: int

    def __post_init__(self) -> None:
        if not 0 < self.k < self.n <= MAX_CODEWORD:
            raise ValueError(f"need 0 < k < n <= {MAX_CODEWORD}, got RS({self.n}, {self.k})")

    @property
    def nsym(self) -> int:
        return self.n - self.k

    def encode(self, data: np.ndarray) -> np.ndarray:
        """(m, k) uint8 messages -> (m, n) systematic codewords."""
        data = np.asarray(data, dtype=np.uint8).reshape(-1, self.k)
        parity = _gf_matmul(data, _parity_matrix(self.k, self.nsym))
        return np.concatenate([data, parity], axis=1)

    def syndromes_clean(self, codewords: np.ndarray) -> np.ndarray:
        """(m, n) codewords -> (m,) bool: True where all syndromes vanish (a valid codeword)."""
        codewords = np.asarray(codewords, dtype=np.uint8).reshape(-1, self.n)
        return ~_gf_matmul(codewords, _syndrome_matrix(self.n, self.nsym)).any(axis=1)

    def decode(
        self, codewords: np.ndarray, erasures: np.ndarray | None = None, margin: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Correct (m, n) codewords; ``erasures`` is an optional (m, n) bool mask of bytes known
        to be unreliable. ``margin`` parity bytes are kept back for detection: corrections need
        ``2 errors + erasures <= n - k - margin``, so a word far from every codeword is far less
        often "corrected" into the wrong one. Returns the (m, k) data and an (m,) bool mask of
        codewords that decoded; the data of the others is left as received."""
        corrected, ok = self.correct(codewords, erasures, margin)
        return corrected[:, : self.k], ok

    def correct(
        self, codewords: np.ndarray, erasures: np.ndarray | None = None, margin: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """``decode``, returning the whole (m, n) corrected codewords, parity included."""
        codewords = np.array(codewords, dtype=np.uint8).reshape(-1, self.n)
        if erasures is None:
            erasures = np.zeros(codewords.shape, dtype=bool)
        erasures = np.asarray(erasures, dtype=bool).reshape(codewords.shape)
        ok = self.syndromes_clean(codewords) & ~erasures.any(axis=1)
        if not ok.all():
            from eventocc.occ.rs_kernel import correct_rows

            ok |= correct_rows(codewords, erasures, ~ok, self.nsym, self.nsym - margin)
        return codewords, ok


# The paper's footnote: the RS code chosen for each payload side N.
PAPER_RS_K = {16: 251, 32: 247, 48: 239, 64: 223, 80: 159, 96: 127}


def paper_rs(cells: int) -> ReedSolomon:
    """The paper's RS(255, k) for payload side ``cells``. Sides the paper did not test use the
    code of the next larger tested side (so protection never drops as N grows), and sides above
    96 use the N = 96 code."""
    side = min((s for s in PAPER_RS_K if s >= cells), default=max(PAPER_RS_K))
    return ReedSolomon(MAX_CODEWORD, PAPER_RS_K[side])
