"""The outer fountain code: a message (with its name, size and sha256) as an endless-looking
series of RaptorQ symbols that any receiver can collect in any order.

**Object.** What is coded is ``size u64 | sha256 (32 bytes) | name length u8 | name (UTF-8)``
followed by the message. The receiver learns name, size and checksum from the object itself and
verifies the checksum before it hands anything out.

**Blocks.** The object is cut into blocks of ``profile.block_symbols`` source symbols, each
RaptorQ coded on its own (RFC 6330 via the ``raptorq`` package), so a 100 MB message only ever
holds the block being sent in memory. The header of each frame names the block and its symbol
count, so a block decodes as soon as ``about block_symbols + 2`` of its symbols arrived.

**Schedule.** The stream makes ``profile.passes`` passes over the blocks. In each pass every
block gets a run of ``k + repair`` consecutive symbols (``repair = ceil(k * repair_ratio) + 2``);
pass 0 sends the source symbols first, later passes send fresh repair symbols only. After the
last pass the stream repeats. A receiver that joins at any moment and loses up to a
``repair / (k + repair)`` share of a run decodes that block from one run.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass
from functools import cache

import raptorq

from eventocc.occ.profiles import LinkProfile

_PREFIX = struct.Struct(">Q32sB")
MAX_NAME_BYTES = 255


@cache
def symbol_size_for(capacity: int) -> int:
    """The RaptorQ symbol size used for ``capacity`` bytes: ``raptorq`` aligns larger symbols
    to 8 bytes, so ask it rather than guess."""
    packet = raptorq.Encoder.with_defaults(b"\0", capacity).get_encoded_packets(0)[0]
    return len(packet) - 4  # minus the PayloadId


def stream_id_of(digest: bytes, name: str) -> int:
    """A 16-bit id from the message's sha256 and name: the same message keeps its id."""
    return int.from_bytes(hashlib.sha256(digest + name.encode()).digest()[:2], "big")


def metadata_prefix(size: int, digest: bytes, name: str) -> bytes:
    raw = name.encode()
    if len(raw) > MAX_NAME_BYTES:
        raise ValueError(f"message name is {len(raw)} bytes of UTF-8; at most {MAX_NAME_BYTES}")
    return _PREFIX.pack(size, digest, len(raw)) + raw


@dataclass(frozen=True)
class Metadata:
    size: int
    sha256: bytes
    name: str
    prefix_size: int

    @classmethod
    def parse(cls, head: bytes) -> Metadata | None:
        """The metadata at the start of an object, or None if ``head`` is too short or garbled."""
        if len(head) < _PREFIX.size:
            return None
        size, digest, name_len = _PREFIX.unpack_from(head)
        end = _PREFIX.size + name_len
        if len(head) < end:
            return None
        try:
            name = head[_PREFIX.size : end].decode()
        except UnicodeDecodeError:
            return None
        return cls(size, digest, name, end)


@dataclass(frozen=True)
class BlockLayout:
    """How an object of ``object_size`` bytes is cut into blocks and scheduled."""

    object_size: int
    symbol_size: int
    profile: LinkProfile

    @property
    def block_bytes(self) -> int:
        return self.profile.block_symbols * self.symbol_size

    @property
    def blocks(self) -> int:
        return math.ceil(self.object_size / self.block_bytes)

    def source_symbols(self, block: int) -> int:
        size = min(self.block_bytes, self.object_size - block * self.block_bytes)
        return math.ceil(size / self.symbol_size)

    def run_length(self, block: int) -> int:
        """Symbols of ``block`` sent in one pass."""
        k = self.source_symbols(block)
        return k + math.ceil(k * self.profile.repair_ratio) + 2

    @property
    def pass_length(self) -> int:
        full = self.run_length(0)
        return full * (self.blocks - 1) + self.run_length(self.blocks - 1)

    @property
    def cycle(self) -> int:
        """Symbols after which the schedule repeats."""
        return self.profile.passes * self.pass_length

    def locate(self, j: int) -> tuple[int, int]:
        """Symbol ``j`` of the stream -> (block, index into the block's packet list)."""
        j %= self.cycle
        pass_, r = divmod(j, self.pass_length)
        block = min(r // self.run_length(0), self.blocks - 1)
        i = r - block * self.run_length(0)
        return block, pass_ * self.run_length(block) + i


class FountainEncoder:
    """Symbol ``j`` of a message, computed on demand; only the current block is kept."""

    def __init__(
        self, message: bytes, digest: bytes, name: str, symbol_size: int, profile: LinkProfile
    ) -> None:
        self.message = memoryview(message)
        self.prefix = metadata_prefix(len(message), digest, name)
        self.layout = BlockLayout(len(self.prefix) + len(message), symbol_size, profile)
        self.overrun = 0
        """Packets made beyond each block's scheduled ones: a packed frame (``run``) that
        starts near the end of its block's last run carries them."""
        self._block: tuple[int, list[bytes]] | None = None

    def _object_bytes(self, lo: int, hi: int) -> bytes:
        """Bytes [lo, hi) of prefix + message, without building the whole object."""
        p = len(self.prefix)
        head = self.prefix[lo:hi] if lo < p else b""
        return head + bytes(self.message[max(lo - p, 0) : max(hi - p, 0)])

    def _packets(self, block: int) -> list[bytes]:
        if self._block is None or self._block[0] != block:
            lay = self.layout
            k, t = lay.source_symbols(block), lay.symbol_size
            start = block * lay.block_bytes
            data = self._object_bytes(start, start + k * t).ljust(k * t, b"\0")
            count = lay.profile.passes * lay.run_length(block) + self.overrun
            packets = raptorq.Encoder.with_defaults(data, t).get_encoded_packets(count - k)
            if packets[-1][0] != 0 or int.from_bytes(packets[-1][1:4], "big") > 0xFFFF:
                raise RuntimeError("RaptorQ split a block; lower LinkProfile.block_symbols")
            self._block = (block, packets)
        return self._block[1]

    def run(self, j: int, count: int) -> tuple[int, int, int, bytes]:
        """(block, source symbols of the block, first esi, bytes) of ``count`` symbols with
        consecutive esis from the one at stream position ``j``, all of ``j``'s block: what a
        packed frame carries (``eventocc.occ.packing``). Past the block's run the esis go on
        into its later passes' repair symbols, which serve a receiver as well as any."""
        if count > self.overrun:
            self.overrun, self._block = count, None
        block, index = self.layout.locate(j)
        packets = self._packets(block)[index : index + count]
        return (
            block,
            self.layout.source_symbols(block),
            int.from_bytes(packets[0][1:4], "big"),
            b"".join(p[4:] for p in packets),
        )

    def symbol(self, j: int) -> tuple[int, int, int, bytes]:
        """(block, source symbols of the block, esi, symbol bytes) of stream symbol ``j``."""
        block, index = self.layout.locate(j)
        packet = self._packets(block)[index]
        return (
            block,
            self.layout.source_symbols(block),
            int.from_bytes(packet[1:4], "big"),
            packet[4:],
        )


class FountainDecoder:
    """Collects the symbols of one stream; ``add`` returns (metadata, message) once verified."""

    def __init__(self, symbol_size: int, profile: LinkProfile) -> None:
        self.symbol_size, self.profile = symbol_size, profile
        self.reset()

    def reset(self) -> None:
        self.decoders: dict[int, raptorq.Decoder] = {}
        self.block_symbols: dict[int, int] = {}
        self.held: dict[int, set[int]] = {}
        self.decoded: dict[int, bytes] = {}
        self.metadata: Metadata | None = None

    @property
    def layout(self) -> BlockLayout | None:
        if self.metadata is None:
            return None
        size = self.metadata.prefix_size + self.metadata.size
        return BlockLayout(size, self.symbol_size, self.profile)

    def progress(self) -> tuple[int, int]:
        """(symbols held, symbols needed): decoded blocks count as complete; blocks not seen
        yet count once the metadata says they exist."""
        need = dict(self.block_symbols)
        if (lay := self.layout) is not None:
            need.update({b: lay.source_symbols(b) for b in range(lay.blocks) if b not in need})
        held = sum(k if b in self.decoded else len(self.held.get(b, ())) for b, k in need.items())
        return held, sum(need.values())

    def add(self, block: int, k: int, esi: int, symbol: bytes) -> tuple[Metadata, bytes] | None:
        if block in self.decoded or self.block_symbols.setdefault(block, k) != k:
            return None  # done already, or a header that contradicts the ones before
        held = self.held.setdefault(block, set())
        if esi in held:
            return None
        held.add(esi)
        if block not in self.decoders:
            self.decoders[block] = raptorq.Decoder.with_defaults(
                k * self.symbol_size, self.symbol_size
            )
        data = self.decoders[block].decode(b"\0" + esi.to_bytes(3, "big") + symbol)
        if data is None:
            return None
        self.decoded[block] = data
        del self.decoders[block], self.held[block]
        if block == 0:
            self.metadata = Metadata.parse(data)
            if self.metadata is None:
                self.reset()  # garbled metadata: only a corrupted symbol can cause it
                return None
        return self._finish()

    def _finish(self) -> tuple[Metadata, bytes] | None:
        lay, meta = self.layout, self.metadata
        if lay is None or meta is None or len(self.decoded) < lay.blocks:
            return None
        obj = b"".join(self.decoded[b] for b in range(lay.blocks))
        message = obj[meta.prefix_size : meta.prefix_size + meta.size]
        if len(self.decoded) != lay.blocks or hashlib.sha256(message).digest() != meta.sha256:
            self.reset()  # some symbol lied: start over rather than hand out wrong bytes
            return None
        return meta, message
