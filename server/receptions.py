"""What receivers sent us, kept in SQLite beside the message store (same file, own tables).

A *reception* is one message a receiver decoded in full: its bytes, their sha256 (computed
again here: bytes that do not match the digest the receiver claims are refused), whether they
hash to the digest their sender sent in-band, and the uploaded message with the same digest, if
any. Poses are kept at the rate the receiver publishes them (decimated for the UI), so a
trajectory survives a server restart, each with whether a frame had proven the receiver's lock
(verified) or not yet (tentative). Each receiver numbers its reports; the server remembers
the highest number it has stored per receiver, so a report replayed from the receiver's spool
after a reconnect is acknowledged again but stored once. Receivers are kept under their public id
(``eventocc.occ.report.public_receiver_id``), never under the secret one they connect with.
"""

from __future__ import annotations

import hashlib
import math
import secrets
import sqlite3
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from eventocc.occ.report import public_receiver_id

SCHEMA = """
CREATE TABLE IF NOT EXISTS receivers (
    id         TEXT PRIMARY KEY,
    first_seen TEXT NOT NULL,
    last_seen  TEXT NOT NULL,
    last_seq   INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS receptions (
    id         TEXT PRIMARY KEY,
    receiver   TEXT NOT NULL REFERENCES receivers(id),
    seq        INTEGER NOT NULL,
    name       TEXT NOT NULL,
    sha256     TEXT NOT NULL,
    size       INTEGER NOT NULL,
    goodput_bps REAL,
    message_id TEXT,
    received   TEXT NOT NULL,
    data       BLOB NOT NULL,
    verified   INTEGER,
    UNIQUE (receiver, seq)
);
CREATE TABLE IF NOT EXISTS receiver_poses (
    receiver TEXT NOT NULL REFERENCES receivers(id),
    t_us     INTEGER NOT NULL,
    tx REAL, ty REAL, tz REAL, qx REAL, qy REAL, qz REAL, qw REAL,
    verified INTEGER,
    PRIMARY KEY (receiver, t_us)
) WITHOUT ROWID;
"""
SCHEMA_VERSION = 1
"""``PRAGMA user_version``: 0 kept receivers under the secret id they connect with, 1 under
their public id."""
RECEIVER_COLUMNS = (("receivers", "id"), ("receptions", "receiver"), ("receiver_poses", "receiver"))
COLUMNS = "id, receiver, seq, name, sha256, size, goodput_bps, message_id, received, verified"

PoseRow = tuple[int, float, float, float, float, float, float, float]
"""``(t_us, tx, ty, tz, qx, qy, qz, qw)``: a TUM row with the time in microseconds."""


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _keep_public_ids(db: sqlite3.Connection) -> None:
    """Rename every receiver kept under its secret id to its public id."""
    for (secret,) in db.execute("SELECT id FROM receivers").fetchall():
        for table, column in RECEIVER_COLUMNS:
            db.execute(
                f"UPDATE {table} SET {column} = ? WHERE {column} = ?",
                (public_receiver_id(secret), secret),
            )


def _mark(db: sqlite3.Connection, receiver: str, seq: int) -> None:
    # In the same transaction as what report ``seq`` stored: both happen or neither.
    db.execute(
        "UPDATE receivers SET last_seq = MAX(last_seq, ?), last_seen = ? WHERE id = ?",
        (seq, datetime.now(UTC).isoformat(), receiver),
    )


@dataclass(frozen=True, slots=True)
class Reception:
    id: str
    receiver: str
    seq: int
    name: str
    sha256: str
    """Computed by the server from the bytes it stored."""
    size: int
    goodput_bps: float | None
    """Message bits over the time since the receiver's first progress report of it."""
    message_id: str | None
    """The uploaded message with the same sha256, if any."""
    received: datetime
    verified: bool | None = None
    """The bytes hash to the sha256 their sender sent in-band; False: nothing checked them
    (``paper`` sends no checksum); None: stored before this was recorded."""

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> Reception:
        return cls(
            **{
                **dict(row),
                "received": datetime.fromisoformat(row["received"]),
                "verified": None if row["verified"] is None else bool(row["verified"]),
            }
        )


class ReceptionStore:
    """Thread-safe: the event loop's worker threads share one connection, one at a time.

    One long-lived connection rather than one per call: closing the last connection to a WAL
    database checkpoints it with an fsync, ~20 ms, which capped the server at ~50 poses/s.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, timeout=10.0, check_same_thread=False)
        self._db.row_factory = sqlite3.Row
        # WAL + NORMAL: a commit survives a crash of the server process (not of the machine)
        # without one fsync per pose.
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        with self._transaction() as db:
            db.executescript(SCHEMA)
            columns = {r["name"] for r in db.execute("PRAGMA table_info(receptions)")}
            if "verified" not in columns:  # a database from before the column
                db.execute("ALTER TABLE receptions ADD COLUMN verified INTEGER")
            columns = {r["name"] for r in db.execute("PRAGMA table_info(receiver_poses)")}
            if "verified" not in columns:  # its poses' flag stays NULL: not known, not verified
                db.execute("ALTER TABLE receiver_poses ADD COLUMN verified INTEGER")
            if db.execute("PRAGMA user_version").fetchone()[0] < 1:
                _keep_public_ids(db)
            db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock, self._db:  # commit on success, roll back on any exception
            yield self._db

    def register(self, receiver: str) -> int:
        """Record that ``receiver`` connected; returns the last report number stored from it."""
        now = datetime.now(UTC).isoformat()
        with self._transaction() as db:
            db.execute(
                "INSERT INTO receivers (id, first_seen, last_seen) VALUES (?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET last_seen = excluded.last_seen",
                (receiver, now, now),
            )
            return db.execute(
                "SELECT last_seq FROM receivers WHERE id = ?", (receiver,)
            ).fetchone()[0]

    def mark_stored(self, receiver: str, seq: int) -> None:
        """Remember that every report of ``receiver`` up to ``seq`` has been handled."""
        with self._transaction() as db:
            _mark(db, receiver, seq)

    def add(
        self,
        *,
        receiver: str,
        seq: int,
        name: str,
        data: bytes,
        claimed_sha256: str,
        goodput_bps: float | None,
        message_id: str | None,
        verified: bool = False,
    ) -> Reception:
        """Store a finished message; a replay of the same (receiver, seq) returns the first.

        Raises ``ValueError`` if ``data`` does not hash to ``claimed_sha256``.
        """
        sha256 = hashlib.sha256(data).hexdigest()
        if not secrets.compare_digest(sha256, claimed_sha256.lower()):
            raise ValueError(f"message {name!r} does not match its sha256: refusing to store it")
        reception = Reception(
            id=secrets.token_hex(6),
            receiver=receiver,
            seq=seq,
            name=name,
            sha256=sha256,
            size=len(data),
            goodput_bps=goodput_bps,
            message_id=message_id,
            received=datetime.now(UTC),
            verified=verified,
        )
        with self._transaction() as db:
            db.execute(
                f"INSERT OR IGNORE INTO receptions ({COLUMNS}, data) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    reception.id,
                    receiver,
                    seq,
                    name,
                    sha256,
                    reception.size,
                    goodput_bps,
                    message_id,
                    reception.received.isoformat(),
                    verified,
                    data,
                ),
            )
            row = db.execute(
                f"SELECT {COLUMNS} FROM receptions WHERE receiver = ? AND seq = ?", (receiver, seq)
            ).fetchone()
        return Reception.from_row(row)

    def get(self, reception_id: str) -> Reception | None:
        with self._transaction() as db:
            row = db.execute(
                f"SELECT {COLUMNS} FROM receptions WHERE id = ?", (reception_id,)
            ).fetchone()
        return Reception.from_row(row) if row else None

    def receptions(self, limit: int = 100) -> list[Reception]:
        """The newest ``limit`` receptions, newest first."""
        with self._transaction() as db:
            rows = db.execute(
                f"SELECT {COLUMNS} FROM receptions ORDER BY received DESC, id LIMIT ?", (limit,)
            ).fetchall()
        return [Reception.from_row(row) for row in rows]

    def content(self, reception: Reception) -> bytes:
        with self._transaction() as db:
            row = db.execute("SELECT data FROM receptions WHERE id = ?", (reception.id,)).fetchone()
        if row is None:
            raise KeyError(f"reception {reception.id} has been deleted")
        return bytes(row["data"])

    def add_poses(
        self, receiver: str, seq: int, rows: Iterable[PoseRow], *, verified: bool
    ) -> None:
        """Append ``(t_us, tx, ty, tz, qx, qy, qz, qw)`` rows sent in report ``seq``, verified
        (a frame had proven the lock) or tentative."""
        with self._transaction() as db:
            db.executemany(
                "INSERT OR IGNORE INTO receiver_poses "
                "(receiver, t_us, tx, ty, tz, qx, qy, qz, qw, verified) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                ((receiver, *row, verified) for row in rows),
            )
            _mark(db, receiver, seq)

    def poses(self, receiver: str, *, tentative: bool = False) -> list[PoseRow] | None:
        """The kept poses of ``receiver`` in time order, as TUM rows with t in microseconds:
        the verified ones, or with ``tentative`` all; None for a receiver that never
        connected."""
        with self._transaction() as db:
            if db.execute("SELECT 1 FROM receivers WHERE id = ?", (receiver,)).fetchone() is None:
                return None
            rows = db.execute(
                "SELECT t_us, tx, ty, tz, qx, qy, qz, qw FROM receiver_poses "
                "WHERE receiver = ? AND (? OR verified) ORDER BY t_us",
                (receiver, tentative),
            ).fetchall()
        # Servers before ``/ws/receiver`` took strict JSON kept non-finite poses (a NaN reads
        # back as NULL): not poses.
        return [tuple(row) for row in rows if all(_finite(v) for v in row[1:])]

    def totals(self) -> tuple[int, int]:
        """(receptions, their bytes), for the metrics."""
        with self._transaction() as db:
            row = db.execute("SELECT COUNT(*), COALESCE(SUM(size), 0) FROM receptions").fetchone()
        return int(row[0]), int(row[1])
