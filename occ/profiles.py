"""Link profiles: how a message becomes the cells of successive display refreshes.

- ``paper``: the paper bit for bit: the message Reed-Solomon coded as its footnote says, then raw
  bits row-major, MSB first, 1 = white, zero-padded to whole frames; data frame then blank frame.
  No header: the receiver must see the data frames in order (see ``eventocc.occ.paper_codec``).
- ``robust`` (default): every data frame is one fountain-code symbol with a header and a CRC,
  Reed-Solomon coded and interleaved over the frame, whitened; data frame then blank frame.
  A receiver can join at any time, lose or repeat frames, and still recover the message.
- ``fast``: ``robust``'s frames sent differentially on every refresh: a cell toggles to send a 1,
  so each refresh carries one symbol and there are no blank frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from eventocc.occ.marker import MAX_CELLS, MIN_CELLS

PROFILE_NAMES = ("paper", "robust", "fast")
DEFAULT_PROFILE = "robust"
MIN_REFRESH_HZ, MAX_REFRESH_HZ = 1.0, 1000.0
"""The display refresh rates a link may run at: what the receiver and the simulator are built
for."""


@dataclass(frozen=True)
class LinkProfile:
    name: str
    data_every: int
    """Display refreshes per data frame: 2 (data frame + blank frame) or 1 (``fast``)."""
    framed: bool = True
    """Frames carry a header, CRC and fountain symbol (``False``: the paper's raw bit stream)."""
    parity_fraction: float = 0.25
    """Share of each Reed-Solomon codeword spent on parity (framed profiles); 0.25 corrects
    about 12% wrong bytes, i.e. ~1% independent bit errors, the paper's dynamic BER."""
    erasure_below: float = 1 / 32
    """A byte with any cell of confidence below this becomes an RS erasure in a codeword its
    bits alone do not decode (the receiver's confidence is a cell's distance from its
    threshold over half the contrast, so this is a 64th of the contrast)."""
    erasure_rounds: int = 3
    """Retries of a failed Reed-Solomon codeword, each with more of its least confident bytes
    erased (``FrameCodec.decode``); 0: erasures from ``erasure_below`` only."""
    block_symbols: int = 1024
    """Fountain source symbols per block: the unit of memory and of RaptorQ encoding."""
    repair_ratio: float = 0.25
    """Repair symbols sent per source symbol in each pass over a block."""
    passes: int = 4
    """Passes over every block (each with fresh repair symbols) before the stream repeats."""
    key_every: int = 0
    """``fast``: every ``key_every``-th refresh resets the differential state to a fixed key
    pattern (it carries no symbol), so frame k costs at most ``key_every`` symbol encodings."""

    @property
    def data_share(self) -> float:
        """Share of display refreshes that carry a data frame (blank and key refreshes carry
        none): the same for every message, however its last key group falls."""
        share = 1 / self.data_every
        return share * (1 - 1 / self.key_every) if self.key_every else share


PROFILES = {
    "paper": LinkProfile("paper", data_every=2, framed=False, parity_fraction=0.0),
    "robust": LinkProfile("robust", data_every=2),
    "fast": LinkProfile("fast", data_every=1, key_every=32),
}


def get_profile(name: str) -> LinkProfile:
    if not isinstance(name, str) or name not in PROFILES:
        raise ValueError(
            f"unknown link profile {name!r}; valid profiles: {', '.join(PROFILE_NAMES)}"
        )
    return PROFILES[name]


@dataclass(frozen=True)
class LinkSettings:
    """What the receiver pipeline must be told about the screen: its link profile, cells and
    refresh rate. Only settings a receiver can be built for exist: any others raise
    ``ValueError`` saying what is wrong, whoever sent them (the settings come over the network
    from whatever says what the screen shows)."""

    profile: str
    cells: int
    refresh_hz: float = 60.0
    """Whole hertz: a page's measured rate wobbles by a fraction of a hertz, which the receiver
    absorbs (it re-times every frame from its own burst) and must not rebuild for."""

    def __post_init__(self) -> None:
        get_profile(self.profile)  # raises with the list of valid names
        cells, hz = self.cells, self.refresh_hz
        if not _is_number(cells, int) or not MIN_CELLS <= cells <= MAX_CELLS:
            raise ValueError(
                f"cells must be a whole number {MIN_CELLS}..{MAX_CELLS}, got {cells!r}"
            )
        if (
            not _is_number(hz, (int, float))
            or not math.isfinite(hz)
            or not MIN_REFRESH_HZ <= round(hz) <= MAX_REFRESH_HZ
        ):
            raise ValueError(
                f"refresh rate must be {MIN_REFRESH_HZ:g}..{MAX_REFRESH_HZ:g} Hz, got {hz!r}"
            )
        object.__setattr__(self, "refresh_hz", float(round(hz)))

    def __str__(self) -> str:
        return f"{self.profile} with {self.cells} cells at {self.refresh_hz:g} Hz"


def _is_number(value: object, kind: type | tuple[type, ...]) -> bool:
    return isinstance(value, kind) and not isinstance(value, bool)
