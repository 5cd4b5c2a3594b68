"""The results file of ``dit-register --pairs``: an append-only log that a run resumes from and others share.

Every line is one JSON record of one pair: its identity (both paths, and each file's size and modification
time, :func:`identity`), the run's settings (:func:`settings_key`), and the result or the error. Nothing ever
cuts or rewrites the file: a line that does not parse (a run killed while writing it, a blank line, a stray
edit) is reported by number and skipped, and a record never starts inside a line cut short, so the two never
merge.

A pair counts as done where a record with its identity and the run's settings holds a finished result (any
verdict level, "probably wrong" included); an error is tried again. Several processes may share one file
(shards of one list, or the same list twice): each holds a lock on the pair it works on (a POSIX byte-range
lock, :func:`pair_lock`, which the system drops when a process dies, ``kill -9`` included) and reads what the
others appended before it starts a pair, so each pair is registered once.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os

#: The byte-range locks live far past any real results file's end: one byte per pair from here, and the byte
#: before it for appending a record.
LOCK_BASE = 1 << 40


class ResultsFile:
    """A results file held open for a run: one descriptor for reading, appending and locking, because a POSIX
    lock is dropped as soon as its process closes any descriptor of the file.

    Attributes:
      path: the file (created where missing).
      records: the records read so far that parse, in file order.
      bad_lines: the numbers (from 1) of the lines read so far that do not parse (blank lines are skipped
        without a word).
    """

    def __init__(self, path: str):
        self.path = path
        self.records: list[dict] = []
        self.bad_lines: list[int] = []
        self._offset = 0
        self._lines = 0
        self._fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)

    def close(self) -> None:
        os.close(self._fd)

    def __enter__(self) -> ResultsFile:
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def read_new(self) -> list[dict]:
        """Reads the whole lines appended since the last read and returns the records among them that parse."""
        size = os.fstat(self._fd).st_size
        data = os.pread(self._fd, size - self._offset, self._offset) if size > self._offset else b""
        end = data.rfind(b"\n") + 1  # a line still being written is read next time
        new = []
        for raw in data[:end].split(b"\n")[:-1]:
            self._lines += 1
            if not raw.strip():  # a blank line holds nothing to lose
                continue
            try:
                record = json.loads(raw)
                if not isinstance(record, dict):
                    raise ValueError
            except ValueError:
                self.bad_lines.append(self._lines)
                continue
            new.append(record)
        self._offset += end
        self.records += new
        return new

    @property
    def cut_short(self) -> bool:
        """Whether the file ends inside a line past what was read (a writer stopped mid-record, or still
        writing)."""
        return os.fstat(self._fd).st_size > self._offset

    def append(self, record: dict) -> None:
        """Appends ``record`` as one line, under the append lock, flushed to disk. Where the file ends inside a
        line (a writer killed mid-record), a newline goes first, so the two never merge; the cut line stays."""
        line = (json.dumps(record) + "\n").encode()
        with self._locked(LOCK_BASE - 1, wait=True):
            size = os.fstat(self._fd).st_size
            if size and os.pread(self._fd, 1, size - 1) != b"\n":
                line = b"\n" + line
            os.write(self._fd, line)
            os.fsync(self._fd)

    def pair_lock(self, index: int, *, wait: bool):
        """Holds the lock of pair ``index`` while the block runs; yields True, or False at once where another
        process holds it and ``wait`` is False."""
        return self._locked(LOCK_BASE + index, wait=wait)

    @contextlib.contextmanager
    def _locked(self, offset: int, *, wait: bool):
        try:
            fcntl.lockf(self._fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB), 1, offset)
        except OSError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.lockf(self._fd, fcntl.LOCK_UN, 1, offset)


def identity(src: str, tgt: str) -> dict:
    """A pair's identity: both absolute paths, and each file's size and modification time (ns); a file that
    cannot be read has None for both."""

    def stat(path: str) -> list:
        try:
            found = os.stat(path)
        except OSError:
            return [None, None]
        return [found.st_size, found.st_mtime_ns]

    return {"src": os.path.abspath(src), "tgt": os.path.abspath(tgt), "src_file": stat(src), "tgt_file": stat(tgt)}


def settings_key(checkpoint: str | None, changes: dict, reading: dict) -> dict:
    """The settings that make two runs' results comparable: the checkpoint, the inference settings changed,
    and how the files were read."""
    return {"checkpoint": None if checkpoint is None else os.path.abspath(checkpoint), **changes, **reading}


def finished(record: dict) -> bool:
    """Whether a record holds a result (any verdict level), not an error."""
    return "error" not in record and "level" in record


def identity_key(pair: dict | None) -> str:
    """A pair's identity (:func:`identity`) as one hashable string, the same for equal identities."""
    return json.dumps(pair, sort_keys=True)
