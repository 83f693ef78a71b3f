"""SQLite message store: message rows over content-addressed blobs.

Every upload gets its own id (its own name, profile and cell count), while the bytes are stored
once per sha256: uploading the same file twice makes two messages sharing one blob. A blob is
deleted with its last message. Each operation runs in one transaction on its own connection
(WAL mode), so the store is safe to share between the server's worker threads and a failed
operation leaves nothing half-written.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import sqlite3
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import astuple, dataclass
from datetime import UTC, datetime
from pathlib import Path

SCHEMA = """
CREATE TABLE IF NOT EXISTS blobs (
    sha256 TEXT PRIMARY KEY,
    data   BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS messages (
    id      TEXT PRIMARY KEY,
    name    TEXT NOT NULL,
    sha256  TEXT NOT NULL REFERENCES blobs(sha256),
    size    INTEGER NOT NULL,
    profile TEXT NOT NULL,
    cells   INTEGER NOT NULL,
    created TEXT NOT NULL,
    facts   TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS messages_by_sha256 ON messages(sha256);
"""
COLUMNS = "id, name, sha256, size, profile, cells, created, facts"


class MessageDeleted(LookupError):
    """The message was deleted after it was looked up (a read racing a delete)."""


@dataclass(frozen=True, slots=True)
class StoredMessage:
    id: str
    name: str
    sha256: str
    size: int
    profile: str
    cells: int
    created: datetime
    """UTC, when the message was uploaded."""
    facts: dict
    """What the encoder reported at upload (JSON), kept so listing never re-reads blobs."""

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> StoredMessage:
        created, facts = datetime.fromisoformat(row["created"]), json.loads(row["facts"])
        return cls(**{**dict(row), "created": created, "facts": facts})

    def __hash__(self) -> int:  # facts is a dict; the id alone identifies a message
        return hash(self.id)


class MessageStore:
    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._transaction() as db:
            db.execute("PRAGMA journal_mode=WAL")  # readers never wait for the writer
            db.executescript(SCHEMA)

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with closing(sqlite3.connect(self.path, timeout=10.0)) as db:
            db.row_factory = sqlite3.Row
            with db:  # commit on success, roll back on any exception
                yield db

    def add(
        self, data: bytes, *, name: str, profile: str, cells: int, facts: dict | None = None
    ) -> StoredMessage:
        """Store ``data`` as a new message; the blob is shared with earlier identical uploads."""
        message = StoredMessage(
            id=secrets.token_hex(6),
            name=name,
            sha256=hashlib.sha256(data).hexdigest(),
            size=len(data),
            profile=profile,
            cells=cells,
            created=datetime.now(UTC),
            facts=facts or {},
        )
        with self._transaction() as db:
            db.execute(
                "INSERT OR IGNORE INTO blobs (sha256, data) VALUES (?, ?)", (message.sha256, data)
            )
            db.execute(
                f"INSERT INTO messages ({COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (*astuple(message)[:-2], message.created.isoformat(), json.dumps(message.facts)),
            )
        return message

    def get(self, message_id: str) -> StoredMessage | None:
        with self._transaction() as db:
            row = db.execute(
                f"SELECT {COLUMNS} FROM messages WHERE id = ?", (message_id,)
            ).fetchone()
        return StoredMessage.from_row(row) if row else None

    def messages(self) -> list[StoredMessage]:
        """All messages, newest first."""
        with self._transaction() as db:
            rows = db.execute(
                f"SELECT {COLUMNS} FROM messages ORDER BY created DESC, id"
            ).fetchall()
        return [StoredMessage.from_row(row) for row in rows]

    def content(self, message: StoredMessage) -> bytes:
        with self._transaction() as db:
            row = db.execute(
                "SELECT data FROM blobs WHERE sha256 = ?", (message.sha256,)
            ).fetchone()
        if row is None:  # its last message was deleted since ``message`` was read
            raise MessageDeleted(f"message {message.id!r} has been deleted")
        return bytes(row["data"])

    def delete(self, message_id: str) -> bool:
        """Delete a message, and its blob if no other message shares it. False if unknown."""
        with self._transaction() as db:
            row = db.execute("SELECT sha256 FROM messages WHERE id = ?", (message_id,)).fetchone()
            if row is None:
                return False
            db.execute("DELETE FROM messages WHERE id = ?", (message_id,))
            db.execute(
                "DELETE FROM blobs WHERE sha256 = ? AND NOT EXISTS "
                "(SELECT 1 FROM messages WHERE sha256 = ?)",
                (row["sha256"], row["sha256"]),
            )
        return True

    def blob_count(self) -> int:
        with self._transaction() as db:
            return db.execute("SELECT COUNT(*) FROM blobs").fetchone()[0]
