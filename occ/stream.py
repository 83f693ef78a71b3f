"""A message as the cell matrices of successive display refreshes, and back.

``StreamEncoder.frame(k)`` is a pure function of (message, profile, geometry, k): nothing is
expanded up front, so a large message costs memory only for the fountain block in flight.

Refresh timeline (60 Hz display):

- optional preamble (the authors' generator): 180 blank refreshes, then 90 pairs of
  [all-white payload + inner locator, blank];
- then the data part, which loops with period ``cycle`` refreshes:
  - ``paper`` / ``robust``: [data frame, blank frame] pairs;
  - ``fast``: one symbol per refresh, sent differentially: the payload shown at refresh k is
    ``s_k = s_{k-1} XOR b_k``, so a cell toggles to send a 1 and the receiver reads ``b_k`` from
    the events of that one transition. The inner locator is shown on even refreshes only, so it
    still blinks at half the refresh rate. Every ``key_every``-th refresh resets the payload to
    all black (its toggles carry no symbol): ``frame(k)`` then costs at most ``key_every`` symbol
    encodings from the last key, and sequential access costs one (the state is cached).

``StreamDecoder.push`` takes the bits read from one data frame (for ``fast``: the toggle bits
``b_k``) and returns the messages completed by it. Framed profiles accept frames lost, repeated,
reordered or from any starting point, and never return bytes whose sha256 does not match the
one the sender sent in-band (``ReceivedMessage.verified``). The ``paper`` profile has no header
and no checksum: its decoder needs ``message_size`` and in-order frames (see
``eventocc.occ.paper_codec``), and what it returns is unchecked.

An empty message is valid: ``paper`` sends one all-black data frame, the framed profiles a
fountain object holding only the name, size and checksum.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

from eventocc.occ.fountain import FountainDecoder, FountainEncoder, stream_id_of
from eventocc.occ.frame_codec import FrameCodec
from eventocc.occ.framing import FrameHeader
from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.packing import FLAG_PACKED, SYMBOL_SIZE, packed_profile, symbols_per_frame
from eventocc.occ.paper_codec import PaperDecoder, PaperEncoder
from eventocc.occ.profiles import DEFAULT_PROFILE, LinkProfile, get_profile

PREAMBLE_BLANK = 180
"""Blank refreshes opening the preamble (3 s at 60 fps)."""
PREAMBLE_BLINK = 180
"""Then refreshes of [all-white data frame, blank frame] pairs (3 s at 60 fps)."""
MAX_STREAM_ID = 0xFFFF


@dataclass(frozen=True)
class ReceivedMessage:
    name: str
    data: bytes
    sha256: str
    """Hex digest of ``data``, computed by the receiver: it identifies the bytes, it checks
    nothing."""
    stream_id: int
    profile: str
    sender_sha256: str | None = None
    """Hex digest the sender sent in-band with the message (the fountain object's metadata of
    the framed profiles); None where the sender sent none (``paper``)."""

    @property
    def verified(self) -> bool:
        """Whether the bytes hash to what the sender sent: False for ``paper``, whose message
        carries no checksum (a wrong Reed-Solomon correction passes unnoticed)."""
        return self.sender_sha256 is not None and self.sender_sha256 == self.sha256


def _check_index(k: int) -> None:
    if k < 0:
        raise ValueError(f"refresh index must be >= 0, got {k}")


class StreamEncoder:
    """The refreshes of one message.

    Attributes: ``geometry`` and ``profile``; ``symbols``, the distinct data frames of one
    cycle; ``cycle``, the refreshes after which the data part repeats (``frame(k) ==
    frame(k + cycle)`` for every k past the preamble; always finite, as the fountain's repair
    symbols are bounded by ``LinkProfile.passes``); ``preamble_length`` in refreshes.
    """

    def __init__(
        self,
        message: bytes,
        *,
        name: str = "",
        profile: str = DEFAULT_PROFILE,
        cells: int = 16,
        ring: int = 0,
        preamble: bool = False,
        stream_id: int | None = None,
        packed: bool = False,
        symbol_start: int = 0,
    ) -> None:
        """``packed``: frames of fixed-size symbols (``eventocc.occ.packing``), the first data
        frame's first symbol at the fountain's stream position ``symbol_start``: a stream that
        changes its density or profile goes on where the last one stopped, sending the same
        message's symbols (framed profiles only)."""
        self.profile: LinkProfile = get_profile(profile)
        self.geometry = MarkerGeometry(cells, ring)
        message = bytes(message)
        self.message = message
        self.name = name
        digest = hashlib.sha256(message).digest()
        if stream_id is None:
            stream_id = stream_id_of(digest, name)
        if not 0 <= stream_id <= MAX_STREAM_ID:
            raise ValueError(f"stream_id must be 0..{MAX_STREAM_ID}, got {stream_id}")
        self.stream_id = stream_id
        self.preamble_length = PREAMBLE_BLANK + PREAMBLE_BLINK if preamble else 0
        if packed and not self.profile.framed:
            raise ValueError(f"the {self.profile.name} profile has no fountain symbols to pack")
        if symbol_start < 0:
            raise ValueError(f"symbol_start must be >= 0, got {symbol_start}")
        self.packed, self.symbol_start = packed, symbol_start
        self.symbols_per_frame = 1
        """Fountain symbols per data frame (more than one only when ``packed``)."""
        if self.profile.framed:
            self._codec = FrameCodec(self.profile, cells)
            size, fountain_profile = self._codec.symbol_size, self.profile
            if packed:
                size, fountain_profile = SYMBOL_SIZE, packed_profile(self.profile)
            self._fountain = FountainEncoder(message, digest, name, size, fountain_profile)
            if packed:
                self.symbols_per_frame = symbols_per_frame(self._codec.room)
            self.symbols = math.ceil(self._fountain.layout.cycle / self.symbols_per_frame)
        else:
            self._paper = PaperEncoder(message, cells)
            self.symbols = self._paper.layout.frames
        if self.profile.key_every:  # whole key groups, the last one wrapping round the symbols
            m = self.profile.key_every
            self.cycle = m * math.ceil(self.symbols / (m - 1))
        else:
            self.cycle = self.profile.data_every * self.symbols
        self._payload_cache: tuple[int, np.ndarray] | None = None
        self._state_cache: tuple[int, np.ndarray] | None = None

    # --- timeline --------------------------------------------------------------------------
    def _data_slot(self, k: int) -> int | None:
        """Refresh ``k``'s slot in the looping data part, or None inside the preamble."""
        _check_index(k)
        if k < self.preamble_length:
            return None
        return (k - self.preamble_length) % self.cycle

    def _symbol_index(self, slot: int) -> int | None:
        """The symbol a data-part slot carries, or None for blank and key refreshes."""
        if self.profile.key_every:
            m = self.profile.key_every
            if slot % m == 0:
                return None
            return (slot - slot // m - 1) % self.symbols
        return None if slot % 2 else slot // 2

    def is_data_frame(self, k: int) -> bool:
        slot = self._data_slot(k)
        return slot is not None and self._symbol_index(slot) is not None

    def payload_bits(self, k: int) -> np.ndarray:
        """(N, N) uint8 bits the receiver should read at data refresh ``k`` (for ``fast``, the
        toggle bits)."""
        slot = self._data_slot(k)
        j = None if slot is None else self._symbol_index(slot)
        if j is None:
            raise ValueError(f"refresh {k} carries no data; check is_data_frame(k) first")
        return self._payload(j).copy()

    def _payload(self, j: int) -> np.ndarray:
        if self._payload_cache is None or self._payload_cache[0] != j:
            if self.packed:
                m = self.symbols_per_frame
                block, k, esi, run = self._fountain.run(self.symbol_start + j * m, m)
                header = FrameHeader(self.stream_id, block, k, esi, FLAG_PACKED)
                bits = self._codec.encode(header, run.ljust(self._codec.room, b"\0"))
            elif self.profile.framed:
                block, k, esi, symbol = self._fountain.symbol(j)
                header = FrameHeader(self.stream_id, block, k, esi)
                bits = self._codec.encode(header, symbol)
            else:
                bits = self._paper.payload(j)
            self._payload_cache = (j, bits)
        return self._payload_cache[1]

    # --- frames ----------------------------------------------------------------------------
    def frame(self, k: int) -> np.ndarray:
        """Bool (side, side): the whole marker's cells at display refresh ``k``."""
        geo = self.geometry
        slot = self._data_slot(k)
        if slot is None:  # preamble
            blink = k - PREAMBLE_BLANK
            if blink >= 0 and blink % 2 == 0:
                return geo.data_frame(np.ones((geo.cells, geo.cells), dtype=bool))
            return geo.blank_frame.copy()
        if self.profile.key_every:
            return geo.data_frame(self._fast_state(slot), locator=slot % 2 == 0)
        j = self._symbol_index(slot)
        if j is None:
            return geo.blank_frame.copy()
        return geo.data_frame(self._payload(j))

    def _fast_state(self, slot: int) -> np.ndarray:
        """The differential payload ``s`` shown at a ``fast`` data-part slot."""
        key = slot - slot % self.profile.key_every
        cached = self._state_cache
        if cached is not None and key < cached[0] <= slot:
            start, state = cached
        else:
            start, state = key, np.zeros((self.geometry.cells,) * 2, dtype=np.uint8)
        for s in range(start + 1, slot + 1):
            state = state ^ self._payload(self._symbol_index(s))
        self._state_cache = (slot, state)
        return state

    def symbol_end(self, refreshes: int) -> int:
        """The stream position a packed stream that changes its settings after showing
        ``refreshes`` refreshes of this one goes on from: at or past every symbol those
        refreshes carried (a few unsent ones skipped cost nothing: the fountain needs any
        symbols, not these)."""
        return self.symbol_start + refreshes * self.symbols_per_frame

    def frames(self, start: int, count: int) -> np.ndarray:
        """(count, side, side) bool: refreshes ``start .. start + count - 1``."""
        _check_index(start)
        if count < 0:
            raise ValueError(f"count must be >= 0, got {count}")
        side = self.geometry.side
        out = np.empty((count, side, side), dtype=bool)
        for i in range(count):
            out[i] = self.frame(start + i)
        return out


class StreamDecoder:
    """Feed it the bits of data frames; it returns each message once (verified against the
    sender's sha256 for the framed profiles, unchecked for ``paper``).

    Framed profiles need nothing but ``profile`` and ``cells``; several streams may be in flight
    at once, told apart by their stream id. ``paper`` frames carry no header, so its decoder
    also needs ``message_size`` (and ``name`` to report): without it, it decodes nothing.
    """

    def __init__(
        self,
        *,
        profile: str | LinkProfile = DEFAULT_PROFILE,
        cells: int = 16,
        message_size: int | None = None,
        name: str = "",
    ) -> None:
        """``profile``: a name, or a profile whose receiver settings (erasures) differ."""
        self.profile = profile if isinstance(profile, LinkProfile) else get_profile(profile)
        self.geometry = MarkerGeometry(cells)
        self.name = name
        self._delivered: set[int] = set()
        """Stream ids already returned: their later frames are ignored."""
        self._streams: dict[int, FountainDecoder] = {}
        self._paper: PaperDecoder | None = None
        if self.profile.framed:
            self._codec = FrameCodec(self.profile, cells)
        elif message_size is not None:
            if message_size < 0:
                raise ValueError(f"message_size must be >= 0, got {message_size}")
            self._paper = PaperDecoder(message_size, cells, self.profile.erasure_below)
        self.frames_pushed = 0
        self.verified_bits = 0
        """Payload bits of the frames whose inner code and CRC passed (framed profiles; the
        ``paper`` frames carry no check): the link's verified throughput, whether or not
        their message was still wanted."""

    def _check(self, array: np.ndarray, what: str) -> np.ndarray:
        array = np.asarray(array)
        n = self.geometry.cells
        if array.shape != (n, n):
            raise ValueError(f"{what} must be {n}x{n}, got shape {array.shape}")
        return array

    def push(self, bits: np.ndarray, confidence: np.ndarray | None = None) -> list[ReceivedMessage]:
        bits = self._check(bits, "bits")
        if confidence is not None:
            confidence = self._check(confidence, "confidence")
        self.frames_pushed += 1
        if self.profile.framed:
            return self._push_framed(bits, confidence)
        return self._push_paper(bits, confidence)

    def _received(
        self, name: str, data: bytes, stream_id: int, sender_sha256: bytes | None
    ) -> list[ReceivedMessage]:
        self._delivered.add(stream_id)
        digest = hashlib.sha256(data).hexdigest()
        sent = None if sender_sha256 is None else sender_sha256.hex()
        return [ReceivedMessage(name, data, digest, stream_id, self.profile.name, sent)]

    def _push_paper(self, bits: np.ndarray, confidence: np.ndarray | None) -> list[ReceivedMessage]:
        paper = self._paper
        if paper is None or 0 in self._delivered:
            return []
        paper.push(bits, confidence)
        if not (paper.complete and paper.pushed):
            return []
        return self._received(self.name, bytes(paper.data), 0, None)

    def _push_framed(
        self, bits: np.ndarray, confidence: np.ndarray | None
    ) -> list[ReceivedMessage]:
        frame = self._codec.decode(bits, confidence)
        if frame is None:
            return []
        header, symbol = frame
        size, profile = self._codec.symbol_size, self.profile
        if header.flags & FLAG_PACKED:
            size, profile = SYMBOL_SIZE, packed_profile(self.profile)
            symbol = symbol[: symbols_per_frame(len(symbol)) * SYMBOL_SIZE]
        self.verified_bits += 8 * len(symbol)
        if header.stream_id in self._delivered:
            return []
        stream = self._streams.get(header.stream_id)
        if stream is None or stream.symbol_size != size:
            # A stream sent at another density unpacked, or packed after unpacked frames: the
            # symbols differ in size, so the frames now on screen start over.
            stream = self._streams[header.stream_id] = FountainDecoder(size, profile)
        done = None
        for r in range(len(symbol) // size):
            piece = symbol[r * size : (r + 1) * size]
            done = stream.add(header.block, header.block_symbols, header.esi + r, piece)
            if done is not None:
                break
        if done is None:
            return []
        del self._streams[header.stream_id]
        meta, data = done
        return self._received(meta.name, data, header.stream_id, meta.sha256)

    def adopt(self, older: StreamDecoder) -> None:
        """Take over what ``older`` collected, as a receiver rebuilt for new link settings
        must: the messages it delivered stay delivered, and the symbols it holds of packed
        streams, which are the same whatever the density and framed profile
        (``eventocc.occ.packing``), go on counting. Symbols of unpacked streams fit only
        their own density and are dropped."""
        if not (self.profile.framed and older.profile.framed):
            return
        self._delivered |= older._delivered
        for sid, stream in older._streams.items():
            if stream.symbol_size == SYMBOL_SIZE and sid not in self._streams:
                self._streams[sid] = stream

    @property
    def corrected(self) -> np.ndarray | None:
        """(cells, cells) bool: the cells whose bits the last pushed frame's Reed-Solomon code
        corrected; None if it did not decode, and for ``paper`` (no code per frame)."""
        return self._codec.corrected if self.profile.framed else None

    def progress(self) -> dict[int, dict]:
        """Per stream in flight: stream_id, symbols_held, symbols_needed, name, size (name and
        size are None until the metadata block decoded)."""
        if self._paper is not None:
            lay = self._paper.layout
            return {
                0: {
                    "stream_id": 0,
                    "symbols_held": min(self._paper.pushed, lay.frames),
                    "symbols_needed": lay.frames,
                    "name": self.name,
                    "size": lay.size,
                }
            }
        out = {}
        for sid, stream in self._streams.items():
            held, needed = stream.progress()
            meta = stream.metadata
            out[sid] = {
                "stream_id": sid,
                "symbols_held": held,
                "symbols_needed": needed,
                "name": meta and meta.name,
                "size": meta and meta.size,
            }
        return out
