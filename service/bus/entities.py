"""Undeclaring zenoh entities at shutdown or when a source is forgotten: the session may already be closing,
which is no error worth more than a debug line."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Protocol

import zenoh

log = logging.getLogger("gcdtrav.service")


class Declared(Protocol):
    def undeclare(self) -> None: ...


def undeclare_all(entities: Iterable[Declared]) -> None:
    for entity in entities:
        try:
            entity.undeclare()
        except zenoh.ZError as err:  # the session may already be closing
            log.debug("undeclare failed: %s", err)
