"""The error every query answer may raise: the caller's mistake, its message sent back as the error reply."""


class QueryError(ValueError):
    """A query that can't be answered; the message is sent back as the error reply."""
