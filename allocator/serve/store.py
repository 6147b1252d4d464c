"""Durable state of the fleet service: orders, AGVs and events in SQLite (WAL mode).

One connection, used only from the service's event loop, so writes are serialised without
locks. Every change is one transaction, committed before the request that made it is answered.
In WAL mode with ``synchronous=NORMAL`` (the default) a committed transaction survives the
death of the process (``kill -9``): it is in the write-ahead log, in the operating system's
page cache. ``synchronous=FULL`` (``agv serve --sync full``) also survives a power cut, at the
cost of an fsync per commit.

Only facts are stored: the orders as accepted (with a canonical copy of their body, to tell a
replay from a conflicting reuse of an id), picked up, delivered or withdrawn; the AGVs' last
reported state; and the event log. The plan (which AGV goes to which open order) is derived
state and is rebuilt from these after a restart.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

__all__ = ["Store", "SCHEMA_VERSION"]

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS orders (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL UNIQUE,
    body TEXT NOT NULL,
    pickup_x REAL NOT NULL, pickup_y REAL NOT NULL,
    dropoff_x REAL NOT NULL, dropoff_y REAL NOT NULL,
    priority INTEGER NOT NULL,
    deadline REAL,
    status TEXT NOT NULL,
    agent TEXT,
    created REAL NOT NULL,
    picked_up REAL,
    delivered REAL,
    withdrawn REAL
);
CREATE INDEX IF NOT EXISTS orders_status ON orders (status);
CREATE TABLE IF NOT EXISTS agents (
    id TEXT PRIMARY KEY,
    x REAL NOT NULL, y REAL NOT NULL,
    status TEXT NOT NULL,
    updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    agent TEXT,
    kind TEXT NOT NULL,
    order_id TEXT
);
"""

_ORDER_COLUMNS = ("id", "seq", "body", "pickup_x", "pickup_y", "dropoff_x", "dropoff_y",
                  "priority", "deadline", "status", "agent", "created", "picked_up",
                  "delivered", "withdrawn")


class Store:
    """The service's SQLite database.

    Parameters
    ----------
    path : str or Path
        The database file (created with its folder's permissions if absent). ``":memory:"``
        for a throw-away store.
    sync : {"normal", "full"}
        SQLite's ``synchronous`` setting in WAL mode: ``normal`` survives a killed process,
        ``full`` a power cut too.

    Raises
    ------
    ValueError
        For a bad ``sync``, a database of another schema version, or a file SQLite cannot open.
    """

    def __init__(self, path: str | Path, sync: str = "normal") -> None:
        if sync not in ("normal", "full"):
            raise ValueError(f"sync must be 'normal' or 'full', got {sync!r}")
        self.path = str(path)
        try:
            self.db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            mode = self.db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            self.db.execute(f"PRAGMA synchronous={sync.upper()}")
            self.db.execute("PRAGMA foreign_keys=ON")
            self.db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as err:
            raise ValueError(f"cannot open the database {self.path}: {err}") from None
        if self.path != ":memory:" and str(mode).lower() != "wal":
            raise ValueError(f"the database {self.path} refused WAL mode (got {mode!r})")
        row = self.db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is None:
            self.db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) != SCHEMA_VERSION:
            raise ValueError(f"the database {self.path} has schema version {row[0]}, this "
                             f"service reads version {SCHEMA_VERSION}")
        self.journal_mode = str(mode).lower()
        self.sync = sync
        self._checkpointer: threading.Thread | None = None
        self._stop = threading.Event()

    def start_checkpointer(self, interval: float = 2.0) -> None:
        """Move the write-ahead log into the database from a background thread (its own
        connection, ``PASSIVE`` checkpoints every ``interval`` seconds) instead of inside a
        commit, where its fsync would hold up the request that triggered it."""
        if self.path == ":memory:" or self._checkpointer is not None:
            return
        self.db.execute("PRAGMA wal_autocheckpoint=0")

        def run() -> None:
            db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            db.execute(f"PRAGMA synchronous={self.sync.upper()}")
            try:
                while not self._stop.wait(interval):
                    try:
                        db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                    except sqlite3.Error:  # busy now: the next round catches up
                        pass
            finally:
                db.close()

        self._checkpointer = threading.Thread(target=run, daemon=True,
                                              name="agv-serve-checkpoint")
        self._checkpointer.start()

    # ------------------------------------------------------------------ transactions
    def write(self, statements: Iterable[tuple[str, tuple[Any, ...]]]) -> None:
        """Run ``(sql, params)`` statements in one transaction and commit it.

        Raises
        ------
        sqlite3.Error
            After rolling back, if any statement or the commit fails.
        """
        db = self.db
        db.execute("BEGIN IMMEDIATE")
        try:
            for sql, params in statements:
                db.execute(sql, params)
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    # ------------------------------------------------------------------ statements
    @staticmethod
    def insert_order(order: dict[str, Any]) -> tuple[str, tuple[Any, ...]]:
        """The INSERT of a new order (a dict with the ``orders`` columns)."""
        cols = ", ".join(_ORDER_COLUMNS)
        marks = ", ".join("?" for _ in _ORDER_COLUMNS)
        return (f"INSERT INTO orders ({cols}) VALUES ({marks})",
                tuple(order.get(c) for c in _ORDER_COLUMNS))

    @staticmethod
    def update_order(order_id: str, **fields: Any) -> tuple[str, tuple[Any, ...]]:
        """An UPDATE of some columns of one order."""
        for name in fields:
            if name not in _ORDER_COLUMNS:
                raise ValueError(f"unknown order column {name!r}")
        sets = ", ".join(f"{name} = ?" for name in fields)
        return f"UPDATE orders SET {sets} WHERE id = ?", (*fields.values(), order_id)

    @staticmethod
    def upsert_agent(agent_id: str, x: float, y: float, status: str,
                     updated: float) -> tuple[str, tuple[Any, ...]]:
        """The INSERT-or-UPDATE of an AGV's reported state."""
        return ("INSERT INTO agents (id, x, y, status, updated) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET x=excluded.x, y=excluded.y, "
                "status=excluded.status, updated=excluded.updated",
                (agent_id, x, y, status, updated))

    @staticmethod
    def insert_event(time: float, agent: str | None, kind: str,
                     order_id: str | None) -> tuple[str, tuple[Any, ...]]:
        """The INSERT of one event-log row."""
        return ("INSERT INTO events (time, agent, kind, order_id) VALUES (?, ?, ?, ?)",
                (time, agent, kind, order_id))

    # ------------------------------------------------------------------ reads
    def orders(self, statuses: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
        """Orders (all, or those with the given statuses), by acceptance order."""
        sql = f"SELECT {', '.join(_ORDER_COLUMNS)} FROM orders"
        params: tuple[Any, ...] = ()
        if statuses is not None:
            sql += f" WHERE status IN ({', '.join('?' for _ in statuses)})"
            params = tuple(statuses)
        rows = self.db.execute(sql + " ORDER BY seq", params).fetchall()
        return [dict(zip(_ORDER_COLUMNS, row, strict=True)) for row in rows]

    def order(self, order_id: str) -> dict[str, Any] | None:
        """One order by id, or None."""
        row = self.db.execute(f"SELECT {', '.join(_ORDER_COLUMNS)} FROM orders WHERE id = ?",
                              (order_id,)).fetchone()
        return None if row is None else dict(zip(_ORDER_COLUMNS, row, strict=True))

    def agents(self) -> list[dict[str, Any]]:
        """Every AGV's last stored state, by id."""
        rows = self.db.execute("SELECT id, x, y, status, updated FROM agents ORDER BY id")
        return [dict(zip(("id", "x", "y", "status", "updated"), r, strict=True)) for r in rows]

    def max_seq(self) -> int:
        """The largest order sequence number (0 for none)."""
        return int(self.db.execute("SELECT COALESCE(MAX(seq), 0) FROM orders").fetchone()[0])

    def counts(self) -> dict[str, int]:
        """Number of orders in each status."""
        rows = self.db.execute("SELECT status, COUNT(*) FROM orders GROUP BY status")
        return {status: int(n) for status, n in rows}

    def close(self) -> None:
        """Stop the checkpoints and close the connection (SQLite checkpoints the WAL here)."""
        self._stop.set()
        if self._checkpointer is not None:
            self._checkpointer.join(5)
        self.db.close()
