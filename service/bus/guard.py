"""Every query gets an answer: a handler that raises still replies, with an error, and the service goes on.

zenoh runs query handlers on its own threads and only logs what escapes them, so a caller would wait for its
timeout and learn nothing. ``answering`` wraps a handler: an unexpected exception becomes the error reply
"internal error: <type>; see the service log", is counted as ``query_failed`` and is logged with its
traceback at the status counters' rate limit. A ``QueryError`` a handler lets out is the caller's mistake:
its sentence is the error reply, counted as ``bad_query``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh
from gcdtrav.schemas.messages import ErrorReply
from gcdtrav.service.bus.replies import reply_error
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.stats import ServiceStats

log = logging.getLogger("gcdtrav.service")

QueryHandler = Callable[[zenoh.Query], None]


def answering(handler: QueryHandler, stats: ServiceStats) -> QueryHandler:
    def answer(query: zenoh.Query) -> None:
        guarded(query, stats, handler)

    return answer


def guarded(query: zenoh.Query, stats: ServiceStats, respond: QueryHandler) -> None:
    """Run ``respond(query)``; whatever it raises becomes the query's error reply. Also for answers sent later
    from another thread (a swap's, from the anchor switch's worker), where nothing else would catch it."""
    try:
        respond(query)
    except QueryError as err:
        stats.rejected(None, "bad_query", f"{query.selector}: {err}"[:300])
        _reply(query, ErrorReply(error=str(err)))
    except Exception as err:
        stats.rejected(None, "query_failed", f"{query.selector}: {type(err).__name__}: {err}"[:300], err)
        _reply(query, ErrorReply(error=f"internal error: {type(err).__name__}; see the service log"))


def answered_later(query: zenoh.Query, stats: ServiceStats, respond: QueryHandler) -> None:
    """``guarded``, from another thread than the query's callback (a swap's answer from the anchor switch's worker,
    a store read's from its reader), then the query dropped: only then does the querier learn that no more replies
    come (else a client collecting the fleet's replies waits for its whole timeout)."""
    try:
        guarded(query, stats, respond)
    finally:
        query.drop()


def _reply(query: zenoh.Query, error: ErrorReply) -> None:
    try:
        reply_error(query, error)
    except Exception as failure:  # the query may have been dropped meanwhile, or the reply itself is broken
        log.debug("error reply to %s failed: %s", query.selector, failure)
