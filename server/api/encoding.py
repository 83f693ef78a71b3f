"""Frame encoders for stored messages: built on demand, a few kept warm in an LRU.

Frame ``k`` of a message is a pure function of (bytes, name, profile, cells, k), so an encoder
never goes stale: the LRU only saves rebuilding it for every batch the transmitter fetches.
"""

from __future__ import annotations

from functools import lru_cache

from fastapi import HTTPException, status

from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import StreamEncoder
from eventocc.server.api.schemas import NOMINAL_REFRESH_HZ, MessagePublic
from eventocc.server.store import MessageStore, StoredMessage


def new_encoder(
    data: bytes,
    *,
    name: str,
    profile: str,
    cells: int,
    packed: bool = False,
    symbol_start: int = 0,
) -> StreamEncoder:
    """The message's encoder; 422 if the link format refuses this message/profile/cells."""
    try:
        return StreamEncoder(
            data,
            name=name,
            profile=profile,
            cells=cells,
            packed=packed,
            symbol_start=symbol_start,
        )
    except ValueError as error:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"cannot send this message with profile {profile!r} and {cells} cells: {error}",
        ) from None


class EncoderCache:
    """``get(message, profile, cells, packed, symbol_start)``: the encoder, rebuilt only when it
    fell out of the LRU."""

    def __init__(self, store: MessageStore, size: int) -> None:
        self._store = store
        self.get = lru_cache(maxsize=size)(self._build)

    def _build(
        self,
        message: StoredMessage,
        profile: str,
        cells: int,
        packed: bool = False,
        symbol_start: int = 0,
    ) -> StreamEncoder:
        data = self._store.content(message)
        return new_encoder(
            data,
            name=message.name,
            profile=profile,
            cells=cells,
            packed=packed,
            symbol_start=symbol_start,
        )


def link_facts(encoder: StreamEncoder) -> dict:
    """What the encoder puts on screen, as stored with the message at upload."""
    return {"frames_per_loop": encoder.cycle, "bits_per_frame": encoder.geometry.bits_per_frame}


def bit_rate_60hz(profile: str, bits_per_frame: int) -> float:
    """The profile's raw cell bits per second at 60 Hz, to 0.1 bit/s: one figure for every
    message of a profile and cell count (computed, not stored, so older uploads agree)."""
    return round(bits_per_frame * NOMINAL_REFRESH_HZ * get_profile(profile).data_share, 1)


def describe(message: StoredMessage) -> MessagePublic:
    facts = {**message.facts}
    facts["bit_rate_60hz"] = bit_rate_60hz(message.profile, facts["bits_per_frame"])
    return MessagePublic(
        id=message.id,
        name=message.name,
        size=message.size,
        sha256=message.sha256,
        profile=message.profile,
        cells=message.cells,
        created=message.created,
        **facts,
    )
