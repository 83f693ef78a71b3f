"""``/api/profiles``: the link profiles and cell counts a message can use."""

from __future__ import annotations

from fastapi import APIRouter

from eventocc.occ.marker import MAX_CELLS, MIN_CELLS
from eventocc.occ.profiles import PROFILE_NAMES
from eventocc.server.api.deps import SettingsDep
from eventocc.server.api.schemas import ProfilesPublic

router = APIRouter(prefix="/profiles", tags=["profiles"])


@router.get("")
def read_profiles(settings: SettingsDep) -> ProfilesPublic:
    return ProfilesPublic(
        profiles=list(PROFILE_NAMES),
        default_profile=settings.default_profile,
        default_cells=settings.default_cells,
        min_cells=MIN_CELLS,
        max_cells=MAX_CELLS,
    )
