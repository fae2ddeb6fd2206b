"""Every query gets an answer: a handler that raises still replies, with an error, and the service goes on.

zenoh runs query handlers on its own threads and only logs what escapes them, so a caller would wait for its
timeout and learn nothing. ``answering`` wraps a handler: an unexpected exception becomes the error reply
"internal error: <type>; see the service log", is counted as ``query_failed`` and is logged with its
traceback at the status counters' rate limit.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh
from gcdtrav.schemas.messages import ErrorReply
from gcdtrav.service.bus.replies import reply_error
from gcdtrav.service.bus.stats import ServiceStats

log = logging.getLogger("gcdtrav.service")

QueryHandler = Callable[[zenoh.Query], None]


def answering(handler: QueryHandler, stats: ServiceStats) -> QueryHandler:
    def answer(query: zenoh.Query) -> None:
        try:
            handler(query)
        except Exception as err:
            stats.rejected(None, "query_failed", f"{query.selector}: {type(err).__name__}: {err}"[:300], err)
            reply = ErrorReply(error=f"internal error: {type(err).__name__}; see the service log")
            try:
                reply_error(query, reply)
            except zenoh.ZError as failure:  # the query may have been dropped meanwhile
                log.debug("error reply to %s failed: %s", query.selector, failure)

    return answer
