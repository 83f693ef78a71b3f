"""Server settings, read from ``EVENTOCC_*`` environment variables (or passed in by tests)."""

from __future__ import annotations

from pathlib import Path
from typing import Self

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from eventocc.occ.link_policy import EVK4_MIN_PX
from eventocc.occ.marker import MAX_CELLS, MIN_CELLS
from eventocc.occ.profiles import DEFAULT_PROFILE, PROFILE_NAMES

MIB = 1 << 20


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="EVENTOCC_", frozen=True)

    data_dir: Path = Path("data")
    """Holds the SQLite database; created on first use."""
    max_upload_bytes: int = Field(64 * MIB, ge=1)
    upload_budget_bytes: int | None = Field(None, ge=1)
    """Bytes of upload bodies held at once over all requests (None: twice ``max_upload_bytes``);
    an upload that would pass it is refused with 503, to retry later. The memory uploads take
    is a small multiple of it: encoding and storing a message copies it."""
    token: SecretStr | None = None
    """When set, writes (upload, delete) need ``Authorization: Bearer <token>``."""
    allowed_origins: list[str] = []
    """Web origins besides the server's own whose pages may change things here and open its
    websockets (``https://screens.example``), e.g. behind a proxy that rewrites Host."""
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    default_profile: str = DEFAULT_PROFILE
    default_cells: int = Field(16, ge=MIN_CELLS, le=MAX_CELLS)
    encoder_cache_size: int = Field(8, ge=1)
    """Frame encoders kept warm, one per (message, profile, cells) being played."""
    auto_min_px_robust: float = Field(EVK4_MIN_PX["robust"], gt=0)
    auto_min_px_fast: float = Field(EVK4_MIN_PX["fast"], gt=0)
    """Pixels per cell auto mode gives each profile before stepping up to it: the EVK4's
    (``occ.link_policy.EVK4_MIN_PX``); a camera that reads smaller cells can be given less."""

    @field_validator("default_profile")
    @classmethod
    def _known_profile(cls, name: str) -> str:
        if name not in PROFILE_NAMES:
            raise ValueError(f"unknown profile {name!r}; choose one of {', '.join(PROFILE_NAMES)}")
        return name

    @model_validator(mode="after")
    def _budget_holds_an_upload(self) -> Self:
        if (
            self.upload_budget_bytes is not None
            and self.upload_budget_bytes < self.max_upload_bytes
        ):
            raise ValueError(
                f"upload_budget_bytes ({self.upload_budget_bytes}) must be at least "
                f"max_upload_bytes ({self.max_upload_bytes}), or no upload of that size could pass"
            )
        return self

    @property
    def upload_budget(self) -> int:
        return self.upload_budget_bytes or 2 * self.max_upload_bytes

    @field_validator("token")
    @classmethod
    def _non_empty_token(cls, token: SecretStr | None) -> SecretStr | None:
        # An empty EVENTOCC_TOKEN= would otherwise silently mean "no token at all".
        if token is not None and not token.get_secret_value():
            raise ValueError("token must not be empty; unset EVENTOCC_TOKEN to disable it")
        return token

    @property
    def db_path(self) -> Path:
        return self.data_dir / "eventocc.db"
