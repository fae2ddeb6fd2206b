"""MCAP recording of the viewer's channels: files in a directory, a new one once the current file passes a
size, each closed cleanly (summary and footer written) so that Foxglove and the ``mcap`` library read it.
With a total cap, the oldest files of this recording are deleted to stay under it."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import foxglove
from foxglove.mcap import MCAPWriteOptions

log = logging.getLogger(__name__)

FILES_UNDER_CAP = 4  # with a total cap, a file is at most cap / 4: about three closed files are kept


class McapRecorder:
    """Records every channel of ``context``. Call ``rotate_if_full`` between messages, ``close`` at the end.

    A file is closed and the next opened once it passes ``file_bytes`` (or ``total_bytes`` / FILES_UNDER_CAP).
    With ``total_bytes``, each rotation deletes the oldest closed files until those kept plus a full current
    file fit under it; only files this recorder wrote are deleted. The caller serialises logging and rotation
    (the viewer holds one lock for both), so no message falls between two files or lands in both.
    """

    def __init__(
        self,
        directory: Path,
        context: foxglove.Context,
        file_bytes: int,
        total_bytes: int | None = None,
        stem: str = "gcdtrav",
        channel_filter: foxglove.SinkChannelFilter | None = None,
    ) -> None:
        self.directory, self.context, self.stem, self.total_bytes = directory, context, stem, total_bytes
        self.channel_filter = channel_filter  # which channels the files get (None: all)
        self.file_bytes = file_bytes if total_bytes is None else min(file_bytes, total_bytes // FILES_UNDER_CAP)
        self.files: list[Path] = []  # on disk, oldest first; the last is being written
        self.deleted: list[Path] = []
        self._opened = 0
        directory.mkdir(parents=True, exist_ok=True)
        # Chunks are flushed to disk as they fill: small enough that the file size tracks what was written.
        self._options = MCAPWriteOptions(chunk_size=max(16 * 1024, min(1 << 20, self.file_bytes // 8)))
        self._writer: foxglove.MCAPWriter | None = None
        self._open_next()

    def _open_next(self) -> None:
        path = self.directory / f"{self.stem}-{time.strftime('%Y%m%d-%H%M%S')}-{self._opened:03d}.mcap"
        self._writer = foxglove.open_mcap(
            path, context=self.context, writer_options=self._options, channel_filter=self.channel_filter
        )
        self._opened += 1
        self.files.append(path)
        log.info("recording to %s", path)

    @property
    def current(self) -> Path:
        return self.files[-1]

    def rotate_if_full(self) -> None:
        if self._writer is not None and self.current.stat().st_size >= self.file_bytes:
            self._writer.close()
            self._delete_oldest()
            self._open_next()

    def _delete_oldest(self) -> None:
        """Delete the oldest closed files until they and a full next file fit under ``total_bytes``."""
        if self.total_bytes is None:
            return
        budget = self.total_bytes - self.file_bytes
        while self.files and sum(path.stat().st_size for path in self.files) > budget:
            oldest = self.files.pop(0)
            oldest.unlink(missing_ok=True)
            self.deleted.append(oldest)
            log.info("deleted %s: the recording passed --record-max-mb", oldest)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
