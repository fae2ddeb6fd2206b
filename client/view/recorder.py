"""MCAP recording of the viewer's channels: files in a directory, a new one once the current file passes a
size, each closed cleanly (summary and footer written) so that Foxglove and the ``mcap`` library read it."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import foxglove
from foxglove.mcap import MCAPWriteOptions

log = logging.getLogger(__name__)


class McapRecorder:
    """Records every channel of ``context``. Call ``rotate_if_full`` between messages, ``close`` at the end.

    The caller serialises logging and rotation (the viewer holds one lock for both), so no message falls
    between two files or lands in both.
    """

    def __init__(self, directory: Path, context: foxglove.Context, max_bytes: int, stem: str = "gcdtrav") -> None:
        self.directory, self.context, self.max_bytes, self.stem = directory, context, max_bytes, stem
        self.files: list[Path] = []
        directory.mkdir(parents=True, exist_ok=True)
        # Chunks are flushed to disk as they fill: small enough that the file size tracks what was written.
        self._options = MCAPWriteOptions(chunk_size=max(64 * 1024, min(1 << 20, max_bytes // 8)))
        self._writer: foxglove.MCAPWriter | None = None
        self._open_next()

    def _open_next(self) -> None:
        path = self.directory / f"{self.stem}-{time.strftime('%Y%m%d-%H%M%S')}-{len(self.files):03d}.mcap"
        self._writer = foxglove.open_mcap(path, context=self.context, writer_options=self._options)
        self.files.append(path)
        log.info("recording to %s", path)

    @property
    def current(self) -> Path:
        return self.files[-1]

    def rotate_if_full(self) -> None:
        if self._writer is not None and self.current.stat().st_size >= self.max_bytes:
            self._writer.close()
            self._open_next()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
