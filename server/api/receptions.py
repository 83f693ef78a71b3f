"""``/api/receptions``: the messages receivers delivered (list, one, their bytes)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Path, Query, status
from fastapi.responses import Response
from pydantic import BaseModel

from eventocc.server.api.deps import LiveDep
from eventocc.server.api.downloads import download
from eventocc.server.receptions import Reception

RECEPTION_ID_PATTERN = r"^[0-9a-f]{12}$"

router = APIRouter(prefix="/receptions", tags=["receptions"])


class ReceptionPublic(BaseModel):
    id: str
    receiver: str
    name: str
    sha256: str
    size: int
    goodput_bps: float | None
    message_id: str | None
    received: datetime
    verified: bool | None
    """The bytes hash to the sha256 their sender sent in-band; False: unchecked (``paper``);
    None: stored before this was recorded."""
    url: str

    @classmethod
    def of(cls, reception: Reception) -> ReceptionPublic:
        fields = {k: getattr(reception, k) for k in cls.model_fields if k != "url"}
        return cls(**fields, url=f"/api/receptions/{reception.id}/content")


class ReceptionsPublic(BaseModel):
    receptions: list[ReceptionPublic]


def get_reception(
    live: LiveDep,
    reception_id: Annotated[str, Path(pattern=RECEPTION_ID_PATTERN, description="Reception id.")],
) -> Reception:
    reception = live.receptions.get(reception_id)
    if reception is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no reception with id {reception_id!r}")
    return reception


ReceptionDep = Annotated[Reception, Depends(get_reception)]


@router.get("")
def read_receptions(
    live: LiveDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100
) -> ReceptionsPublic:
    receptions = live.receptions.receptions(limit)
    return ReceptionsPublic(receptions=[ReceptionPublic.of(r) for r in receptions])


@router.get("/{reception_id}")
def read_reception(reception: ReceptionDep) -> ReceptionPublic:
    return ReceptionPublic.of(reception)


@router.get("/{reception_id}/content", response_class=Response)
def download_reception(reception: ReceptionDep, live: LiveDep) -> Response:
    """The bytes under the name the receiver decoded (the transmitter's, any characters)."""
    return download(live.receptions.content(reception), reception.name or reception.id)
