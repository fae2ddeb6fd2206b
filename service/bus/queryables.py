"""What the queryables answer, besides the status: a source's patch and ground-grid cell, the anchor set, its
history and rollback. Handlers answer from memory, or hand a swap to the AnchorSwitch's worker and reply
from there. A ``QueryError`` they let out becomes the caller's error reply in ``guard.answering``."""

from __future__ import annotations

from collections.abc import Callable

import zenoh
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import AnchorSetRejection, AnchorSetReply, Message
from gcdtrav.schemas.settings import RiskSettings
from gcdtrav.service.bus import replies
from gcdtrav.service.bus.guard import answered_later
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.fleet.anchor_switch import ActivationLost, AnchorSwitch, SwapDone
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.queries import PATCH_FORMS, answer_patch_query, parse_number, strict_parameters
from gcdtrav.service.runtime.stats import ServiceStats

ROLLBACK_FORM = (
    "steps=N (1 = the set before the active one)[;instance=NAME (only that instance rolls back)]"
    "[;expected=VERSION (only if that set is active)]"
)
SWAP_FORM = (
    "[expected=VERSION (only if that set is active)] with a payload, or proposal=VERSION[;expected=V][;force=true]"
)
SWAP_PARAMETERS = {"expected", "force", "proposal"}


def answer_later(
    query: zenoh.Query, key: str, stats: ServiceStats
) -> Callable[[Message | None, BaseException | None], None]:
    """Reply to ``query`` once a job on the anchor switch's reader is done: its message, or its error as the
    query's error reply (``guarded``: a QueryError is the caller's sentence, anything else an internal error)."""

    def respond(query: zenoh.Query, message: Message | None, error: BaseException | None) -> None:
        if error is not None:
            raise error
        assert message is not None
        replies.reply(query, key, message)

    return lambda message, error: answered_later(query, stats, lambda query: respond(query, message, error))


def parse_flag(text: str, name: str) -> bool:
    if text not in ("true", "false"):
        raise QueryError(f"parameter '{name}' is '{text}'; give {name}=true or {name}=false")
    return text == "true"


class SourceQueries:
    """``{prefix}/out/{source}/patch`` from the frame history, ``.../cell`` from the ground grids."""

    def __init__(
        self,
        keys: Keys,
        history: FrameHistory,
        grids: GridOutputs | None,
        owns: Callable[[str], bool],
        risk: RiskSettings | None = None,
    ) -> None:
        self.keys, self.history, self.grids, self.owns = keys, history, grids, owns
        self.risk = risk or RiskSettings()

    def on_patch(self, query: zenoh.Query) -> None:
        source = self._owned_source(query, "patch")
        if source is not None:
            params = strict_parameters(replies.without_format(query), PATCH_FORMS)
            replies.reply(query, str(query.key_expr), answer_patch_query(self.history, source, params, self.risk))

    def on_cell(self, query: zenoh.Query) -> None:
        source = self._owned_source(query, "cell")
        if source is not None and self.grids is not None:
            answer = self.grids.answer(source, replies.text_without_format(str(query.parameters)), self.risk)
            replies.reply(query, str(query.key_expr), answer)

    def _owned_source(self, query: zenoh.Query, kind: str) -> str | None:
        """The source a query names; None if another instance owns it (the owner answers: replying too
        would race it)."""
        key = str(query.key_expr)
        source = self.keys.source_of(key, kind)
        if source is None:
            example = self.keys.patch("r1/front") if kind == "patch" else self.keys.cell("r1/front")
            raise QueryError(f"query one source's {kind} key, e.g. {example}, not '{key}'")
        if not self.owns(source):
            return None
        replies.check_format(query)
        return source


class AnchorQueries:
    """``{prefix}/config/anchors`` (get, or swap with a body), its ``history`` and ``rollback``."""

    def __init__(self, keys: Keys, switch: AnchorSwitch, stats: ServiceStats) -> None:
        self.keys, self.switch, self.stats = keys, switch, stats

    def on_anchors(self, query: zenoh.Query) -> None:
        """Get the active set (no payload, no parameter), swap it (a payload), or apply a kept proposal
        (``proposal=VERSION``); ``expected=VERSION``: only if that set is still the active one (compare-and-swap).
        The swap runs on the switch's worker, not here."""
        replies.check_format(query)
        params = strict_parameters(replies.without_format(query), SWAP_FORM)
        if set(params) - SWAP_PARAMETERS:
            raise QueryError(f"unknown parameter(s) {sorted(set(params) - SWAP_PARAMETERS)}; give {SWAP_FORM}")
        payload = query.payload.to_bytes() if query.payload is not None else b""
        expected, force = params.get("expected"), parse_flag(params.get("force", "false"), "force")
        done = self._swap_answer(query, self.keys.anchors)
        if "proposal" in params:
            if payload:
                raise QueryError("give either an anchor set as payload or proposal=VERSION, not both")
            self.switch.submit_proposal(params["proposal"], expected, force, done)
        elif payload:
            if force:
                raise QueryError("force=true goes with proposal=VERSION (a set of your own needs no force)")
            self.switch.submit(payload, done, expected)
        elif params:
            raise QueryError(f"expected and force go with a swap: {SWAP_FORM}")
        else:
            active = self.switch.head().anchor_set
            replies.reply(query, self.keys.anchors, self._set_reply(active))

    def on_rollback(self, query: zenoh.Query) -> None:
        replies.check_format(query)
        params = strict_parameters(replies.without_format(query), ROLLBACK_FORM)
        if set(params) - {"steps", "instance", "expected"}:
            unknown = sorted(set(params) - {"steps", "instance", "expected"})
            raise QueryError(f"unknown parameter(s) {unknown}; give {ROLLBACK_FORM}")
        steps = int(parse_number(params.get("steps", "1"), "steps", int))
        if params.get("instance", self.switch.instance) != self.switch.instance:
            return  # addressed to another instance of the fleet (the one holding its newest set): no reply
        self.switch.submit_rollback(steps, self._swap_answer(query, self.keys.anchor_rollback), params.get("expected"))

    def on_history(self, query: zenoh.Query) -> None:
        replies.check_no_parameters(query)
        self.switch.read_later(self.switch.history, answer_later(query, self.keys.anchor_history, self.stats))

    def _set_reply(self, anchors: AnchorSet) -> AnchorSetReply:
        head = self.switch.head()
        accepted_at = head.accepted_at if head.version == anchors.version else None
        return AnchorSetReply(
            anchor_set=anchors, version=anchors.version, instance=self.switch.instance, accepted_at=accepted_at
        )

    def _swap_answer(self, query: zenoh.Query, key: str) -> SwapDone:
        """Reply to a swap or rollback query once the switch's worker is done with it."""

        def answer(anchors: AnchorSet | None, error: BaseException | None) -> None:
            answered_later(query, self.stats, lambda query: respond(query, anchors, error))

        def respond(query: zenoh.Query, anchors: AnchorSet | None, error: BaseException | None) -> None:
            if anchors is not None:
                replies.reply(query, key, self._set_reply(anchors))
                return
            lost_to = error.winner.version if isinstance(error, ActivationLost) else None
            if isinstance(error, AnchorSetError):
                messages, reason = error.messages, "lost_activation" if lost_to else "invalid_anchor_set"
            else:
                messages, reason = [f"swap failed: {type(error).__name__}: {error}"], "swap_failed"
            self.stats.rejected(None, reason, "; ".join(messages)[:300], None if reason != "swap_failed" else error)
            rejection = AnchorSetRejection(
                errors=messages,
                active_version=self.switch.head().version,
                instance=self.switch.instance,
                lost_to=lost_to,
            )
            replies.reply_error(query, rejection)

        return answer
