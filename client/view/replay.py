"""What a viewer that connects late still needs to see: the last log lines, and the operator questions still
open (whatever arrives on ``{prefix}/out/{source}/question``, forwarded as JSON, until an answer with its id
arrives on ``{prefix}/in/{source}/answer``)."""

from __future__ import annotations

import base64
import hashlib
import json
import threading
from collections import OrderedDict, deque
from typing import Any, Generic, TypeVar

import msgpack

T = TypeVar("T")
LOG_LINES_KEPT = 50  # replayed to a viewer that subscribes to the log
QUESTIONS_KEPT = 20  # per source: the newest questions, replayed to a viewer that subscribes
QUESTION_SCHEMA = {
    "type": "object",
    "title": "gcdtrav.OperatorQuestion",
    "description": "What the service asks the operator, as it arrived on {prefix}/out/{source}/question "
    "(msgpack or JSON), as JSON; bytes as base64.",
    "properties": {},
}  # no fields listed: the message is forwarded whatever its fields; Lichtblick's parser reads this


class Recent(Generic[T]):
    """The last ``size`` items, thread-safe."""

    def __init__(self, size: int) -> None:
        self._items: deque[T] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, item: T) -> None:
        with self._lock:
            self._items.append(item)

    def items(self) -> list[T]:
        with self._lock:
            return list(self._items)


def jsonable(value: Any) -> Any:
    """msgpack's values as JSON's: bytes as base64 text, map keys as text."""
    if isinstance(value, bytes):
        return base64.b64encode(value).decode()
    if isinstance(value, dict):
        return {str(key): jsonable(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(item) for item in value]
    return value


def question_json(payload: bytes) -> dict[str, Any]:
    """A question payload (a msgpack map, else a JSON object) as a JSON object; ValueError otherwise."""
    try:
        message = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except (ValueError, msgpack.UnpackException, TypeError):
        try:
            message = json.loads(payload)
        except ValueError:
            raise ValueError("a question must be a msgpack map or a JSON object") from None
    if not isinstance(message, dict):
        raise ValueError(f"a question must be a map, got {type(message).__name__}")
    return dict(jsonable(message))


def question_id(question: dict[str, Any]) -> str:
    """Its ``id`` (or ``question_id``) when it has one, else a digest of its content: a question sent again
    replaces itself."""
    for key in ("id", "question_id"):
        if isinstance(question.get(key), str | int):
            return str(question[key])
    return hashlib.sha1(json.dumps(question, sort_keys=True).encode()).hexdigest()


class OpenQuestions:
    """Per source, the newest QUESTIONS_KEPT questions by id, oldest first."""

    def __init__(self) -> None:
        self._by_source: dict[str, OrderedDict[str, dict[str, Any]]] = {}
        self._lock = threading.Lock()

    def add(self, source: str, question: dict[str, Any]) -> None:
        with self._lock:
            kept = self._by_source.setdefault(source, OrderedDict())
            key = question_id(question)
            kept.pop(key, None)
            kept[key] = question
            while len(kept) > QUESTIONS_KEPT:
                kept.popitem(last=False)

    def answered(self, source: str, identifier: str) -> bool:
        """Forget the question ``identifier`` of ``source`` (its answer came); whether it was open."""
        with self._lock:
            return self._by_source.get(source, OrderedDict()).pop(identifier, None) is not None

    def of(self, source: str) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._by_source.get(source, {}).values())
