"""A text file written a row at a time, for the outputs a run streams as frames are processed
(``trajectory.txt``, ``tracking.csv``): each row is on disk when ``write`` returns, so a run that
stops keeps the rows of the frames done, and a row that cannot be written (a full disk) is taken
back, so the file never ends in half a row.
"""
from __future__ import annotations

import os
from pathlib import Path


class RowFile:
    """Rows of text appended to ``path`` (created or emptied), each written through to the file
    (unbuffered). A file-like object for ``csv.writer`` and ``print``-style writers.

    A write that fails (no space left, a file size limit) truncates the file back to its last whole
    row and raises the OSError naming ``path``.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        self._size = 0      # bytes of the whole rows written

    def write(self, text: str) -> int:
        """Append ``text`` (one or more whole rows); returns its length in characters."""
        assert self._fd is not None, "file closed"
        data = text.encode("utf-8")
        done = 0
        try:
            while done < len(data):     # a disk filling up writes part of it, then refuses
                done += os.write(self._fd, data[done:])
        except OSError as err:
            os.ftruncate(self._fd, self._size)
            raise OSError(err.errno, err.strerror, str(self.path)) from None
        self._size += len(data)
        return len(text)

    def flush(self) -> None:
        """(Every row is written through already.)"""

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
