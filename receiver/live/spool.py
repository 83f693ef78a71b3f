"""The daemon's outbox on disk: reports that must reach the server, kept until it acknowledges.

An SQLite file in the output folder. ``append`` numbers each report (AUTOINCREMENT never reuses
a number, even after a daemon restart), the publisher sends pending rows in order, and the
server's cumulative acknowledgement deletes them. So while the server is away, or when the
daemon is killed, finished messages and poses wait here rather than being lost. The file also
keeps the receiver's identity, so a restarted daemon is the same receiver to the server.
"""

from __future__ import annotations

import secrets
import sqlite3
import threading
from pathlib import Path

SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    seq    INTEGER PRIMARY KEY AUTOINCREMENT,
    report TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS identity (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
"""


class Spool:
    """Thread-safe: the pipeline thread appends while the publisher thread reads and deletes."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, timeout=10.0, check_same_thread=False)
        with self._lock, self._db:
            self._db.execute("PRAGMA journal_mode=WAL")
            # NORMAL: a commit survives the daemon being killed, without an fsync per pose.
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(SCHEMA)
            self._db.execute(
                "INSERT OR IGNORE INTO identity VALUES ('receiver_id', ?)", (secrets.token_hex(8),)
            )
            self.receiver_id: str = self._db.execute(
                "SELECT value FROM identity WHERE key = 'receiver_id'"
            ).fetchone()[0]
            """Made once, on the first run in this output folder: the server knows us by it."""

    def append(self, report_json: str) -> int:
        """Keep one report (JSON text) until acknowledged; returns its sequence number."""
        with self._lock, self._db:
            return self._db.execute(
                "INSERT INTO outbox (report) VALUES (?)", (report_json,)
            ).lastrowid

    def pending(self, after_seq: int = 0, limit: int = 256) -> list[tuple[int, str]]:
        """Unacknowledged reports numbered above ``after_seq``, oldest first."""
        with self._lock:
            return self._db.execute(
                "SELECT seq, report FROM outbox WHERE seq > ? ORDER BY seq LIMIT ?",
                (after_seq, limit),
            ).fetchall()

    def acknowledge(self, seq: int) -> None:
        """The server has stored every report up to ``seq``: forget them."""
        with self._lock, self._db:
            self._db.execute("DELETE FROM outbox WHERE seq <= ?", (seq,))

    def __len__(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0]

    def close(self) -> None:
        with self._lock:
            self._db.close()
