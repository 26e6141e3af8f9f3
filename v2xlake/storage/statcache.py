"""Checksums of delivered files remembered across processes, keyed by the file's stat.

Why: deciding that a clip's ingest is current means knowing that its bags are the bytes it
ingested. Hashing them again costs a full read: a CATS-V2V clip's bags are 10-200 GB, minutes
per clip on every scheduled scan of the landing folders. A file whose device, inode, size and
modification time (ns) are unchanged is taken to be unchanged — the rule ``rsync``, ``make``
and git's index (with ``core.trustctime=false``) rely on. The inode is part of the key, so a
file replaced by another (``mv``, a new delivery under the same name) is hashed again even
when its size and mtime happen to match.

The cache is a SQLite file under ``$V2XLAKE_HOME/cache`` (``V2XLAKE_CHECKSUM_CACHE`` names
another file; ``off`` disables it). It never decides anything on its own: any error reading or
writing it falls back to hashing the file, and it is outside every lake, so a refused delivery
still touches nothing of the clip it claimed.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
from pathlib import Path

from v2xlake.storage import checksum

ENV = "V2XLAKE_CHECKSUM_CACHE"
_LOCK = threading.Lock()
_MEMO: dict[tuple[str, int, int, int, int], str] = {}
_DB: dict[str, sqlite3.Connection] = {}


def cache_file() -> Path | None:
    """Where the cache lives (None: disabled)."""
    value = os.environ.get(ENV, "")
    if value.lower() in ("off", "0", "false", "no"):
        return None
    if value:
        return Path(value).expanduser()
    home = Path(os.environ.get("V2XLAKE_HOME", "~/.v2xlake")).expanduser()
    return home / "cache" / "checksums.sqlite"


def _connect(path: Path) -> sqlite3.Connection:
    con = _DB.get(str(path))
    if con is None:
        path.parent.mkdir(parents=True, exist_ok=True)
        # several processes (Dask workers, a scheduler) share it: WAL lets readers go on
        # while one writes, and the timeout waits out a writer instead of failing
        con = sqlite3.connect(path, timeout=10, check_same_thread=False,
                              isolation_level=None)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("CREATE TABLE IF NOT EXISTS checksums (path TEXT, dev INTEGER, "
                    "ino INTEGER, size INTEGER, mtime_ns INTEGER, checksum TEXT NOT NULL, "
                    "PRIMARY KEY (path, dev, ino, size, mtime_ns))")
        _DB[str(path)] = con
    return con


def file_checksum(path: str | Path) -> str:
    """``storage.checksum.of_file(path)``, read from the cache when the file's stat matches
    what was hashed before (in this process or, through the cache file, in an earlier one)."""
    real = str(Path(path).resolve())
    st = os.stat(real)
    key = (real, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    if key in _MEMO:
        return _MEMO[key]
    db = cache_file()
    found: str | None = None
    if db is not None:
        with _LOCK, contextlib.suppress(sqlite3.Error, OSError):
            row = _connect(db).execute(
                "SELECT checksum FROM checksums WHERE path=? AND dev=? AND ino=? AND size=? "
                "AND mtime_ns=?", key).fetchone()
            found = row[0] if row else None
    if found is None:
        found = checksum.of_file(real)
        if db is not None and os.stat(real).st_mtime_ns == st.st_mtime_ns:  # not mid-write
            with _LOCK, contextlib.suppress(sqlite3.Error, OSError):
                con = _connect(db)
                con.execute("DELETE FROM checksums WHERE path=?", (real,))
                con.execute("INSERT OR REPLACE INTO checksums VALUES (?, ?, ?, ?, ?, ?)",
                            (*key, found))
    _MEMO[key] = found
    return found
