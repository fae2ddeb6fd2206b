"""Every key of the protocol, built and parsed in one place (docs/messages.md lists the same keys).

A service with prefix ``gcdtrav`` (the default) answers and publishes on:

  {prefix}/out/{source}/maps                 MapsMessage per processed frame
  {prefix}/out/{source}/maps8                CompactMapsMessage (8-bit T and U, for slow links), when subscribed
  {prefix}/out/{source}/preview              colourised JPEG (T overlay | U)
  {prefix}/out/{source}/patch                queryable: a map patch's or region's ContextDistribution
  {prefix}/out/{source}/grid                 GridMessage (ground grid); .../grid/occupancy, .../grid/uncertainty,
                                             .../grid/gridmap (grid_map_msgs/GridMap), .../grid/costmap (Nav2)
  {prefix}/out/{source}/cell                 queryable: a ground cell's ContextDistribution, or a path
  {prefix}/out/{source}/calibration          queryable: CalibrationReport of the grid's experience (issue 33)
  {prefix}/out/{source}/question             OperatorQuestion: cells ahead stayed ambiguous or novel
  {prefix}/config/anchors                    queryable: the active anchor set, or a swap (payload = new set)
  {prefix}/config/anchors/history            queryable: the last accepted sets
  {prefix}/config/anchors/rollback           queryable: go back N sets
  {prefix}/config/anchors/proposal           queryable: AnchorProposal fitted on the experience (never applied)
  {prefix}/config/experience/exclusions      queryable: the robots excluded from the experience (ExclusionList), or
                                             an ExclusionRequest as payload: exclude or include one (since 1.7)
  {prefix}/config/experience/kept            queryable: StoreContents, what the fleet's store keeps (since 1.7)
  {prefix}/status                            queryable: ServiceStatus
  {prefix}/alive/{instance}                  liveliness token
  {prefix}/member/{instance}/{fingerprint}/{state}/{millis}  liveliness token: the instance's model fingerprint and
                                             whether it serves (service/runtime/fleet/fleet_models.py); since 1.4
  {prefix}/active/{instance}/{millis}/{version}  liveliness token: the instance's active anchor set, accepted at
                                             {millis} (ms since epoch); the fleet converges to the newest
  {prefix}/credit/{source}                   CreditGrant: the source's owner is ready for its next frame

Robots and operators send on (experience enabled; docs/calibration.md):

  {prefix}/in/{source}/outcome               TraversalOutcome: how driving over a place went
  {prefix}/in/{source}/answer                OperatorAnswer (put), or a query with it as payload (AnswerReply)
  {prefix}/in/{source}/planned_path          PlannedPath: a planner's path ahead, where questions look (ask:)

A relay on a robot (``gcdtrav relay``) publishes on the robot's own bus:

  {prefix}/relay/{source}/health             RelayHealth: map age, credits and link figures of one camera (also
                                             sent over the link every link_health_period_s: the service hears it)
  {prefix}/relay/{source}/parked             CameraParked, from the robot's software: the camera stopped on purpose

Robots publish images on ``input_key(input_prefix, source)``. A source name may hold slashes
(``robot1/front``); ``source_of`` recovers it from an output key, ``input_source_of`` from an input key.
"""

from __future__ import annotations

from dataclasses import dataclass

OUTPUT_KINDS = ("maps", "maps8", "preview", "patch", "grid", "cell", "calibration", "question")
# The last chunk of {prefix}/in/{source}/<kind> keys that carry messages, not images: never a camera source.
INPUT_MESSAGE_KINDS = ("outcome", "outcomes", "answer", "planned_path")
NO_FINGERPRINT = "-"  # a member token's fingerprint chunk when the backend has none (key chunks cannot be empty)
GRID_LAYERS = ("occupancy", "uncertainty", "gridmap", "costmap")  # the grid's CDR messages, under .../grid/


@dataclass(frozen=True)
class Keys:
    """The keys under one service prefix. ``source`` may be a key expression (``*``, ``**``) where subscribing."""

    prefix: str = "gcdtrav"

    @property
    def outputs(self) -> str:
        """Everything the service publishes or answers per source: ``{prefix}/out/**``."""
        return f"{self.prefix}/out/**"

    def output(self, source: str, kind: str) -> str:
        if kind not in OUTPUT_KINDS:
            raise ValueError(f"unknown output kind '{kind}'; one of {', '.join(OUTPUT_KINDS)}")
        return f"{self.prefix}/out/{source}/{kind}"

    def maps(self, source: str) -> str:
        return self.output(source, "maps")

    def maps8(self, source: str) -> str:
        """The compact maps: 8-bit T and U, published only while someone subscribes."""
        return self.output(source, "maps8")

    def preview(self, source: str) -> str:
        return self.output(source, "preview")

    def patch(self, source: str) -> str:
        return self.output(source, "patch")

    def grid(self, source: str, layer: str = "") -> str:
        """The ground grid, or one of its ROS messages (``occupancy``, ``uncertainty``, ``gridmap``, ``costmap``)."""
        return self.output(source, "grid") + (f"/{layer}" if layer else "")

    def cell(self, source: str) -> str:
        return self.output(source, "cell")

    def calibration(self, source: str) -> str:
        return self.output(source, "calibration")

    def question(self, source: str) -> str:
        return self.output(source, "question")

    def outcome(self, source: str) -> str:
        """Where traversal outcomes of the grid ``source`` arrive (``**`` where subscribing)."""
        return f"{self.prefix}/in/{source}/outcome"

    def outcomes(self, source: str) -> str:
        """Where a relay's batches of outcomes measured on the robot arrive (``OutcomeBatch``; since 1.6)."""
        return f"{self.prefix}/in/{source}/outcomes"

    def answer(self, source: str) -> str:
        """Where an operator's answers to ``source``'s questions arrive (put, or a query with the answer)."""
        return f"{self.prefix}/in/{source}/answer"

    def planned_path(self, source: str) -> str:
        """Where a planner puts the path ``source`` will drive: questions look along it (docs/calibration.md)."""
        return f"{self.prefix}/in/{source}/planned_path"

    def input_message(self, key: str) -> tuple[str, str] | None:
        """(source, kind) of ``{prefix}/in/{source}/outcome``, ``.../outcomes``, ``.../answer`` or
        ``.../planned_path``; None for any other key (an image's). Such keys are never read as images, whatever the
        inputs' expressions cover."""
        head = f"{self.prefix}/in/"
        source, _, kind = key[len(head) :].rpartition("/") if key.startswith(head) else ("", "", "")
        if kind not in INPUT_MESSAGE_KINDS or not source or "*" in source or "$" in source:
            return None
        return source, kind

    @property
    def anchors(self) -> str:
        return f"{self.prefix}/config/anchors"

    @property
    def anchor_history(self) -> str:
        return f"{self.anchors}/history"

    @property
    def anchor_rollback(self) -> str:
        return f"{self.anchors}/rollback"

    @property
    def anchor_proposal(self) -> str:
        return f"{self.anchors}/proposal"

    @property
    def exclusions(self) -> str:
        """Operators' exclusions of a robot's pairs from calibration and fits (operator-only, like config/**)."""
        return f"{self.prefix}/config/experience/exclusions"

    @property
    def kept(self) -> str:
        """What the fleet's store keeps: raw pairs per source, calibration sums (operator-only, like config/**)."""
        return f"{self.prefix}/config/experience/kept"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    def alive(self, instance: str = "*") -> str:
        return f"{self.prefix}/alive/{instance}"

    def credit(self, source: str) -> str:
        """Where the owner of ``source`` grants it a frame (``source`` may be ``**`` where subscribing)."""
        return f"{self.prefix}/credit/{source}"

    def relay_health(self, source: str) -> str:
        """A robot relay's freshness and link figures for one camera, on the robot's bus."""
        return f"{self.prefix}/relay/{source}/health"

    def relay_parked(self, source: str) -> str:
        """Where the robot's own software tells its relay a camera is parked (stopped on purpose) or runs again."""
        return f"{self.prefix}/relay/{source}/parked"

    def relay_health_source_of(self, key: str) -> str | None:
        """The source in ``{prefix}/relay/{source}/health``; None when the key is not of that form."""
        return _literal_between(key, f"{self.prefix}/relay/", "/health")

    def credit_source_of(self, key: str) -> str | None:
        """The source in ``{prefix}/credit/{source}``; None when the key is not of that form."""
        return _literal_between(key, f"{self.prefix}/credit/", "")

    def source_of(self, key: str, kind: str) -> str | None:
        """The source in ``{prefix}/out/{source}/{kind}``; None when the key is not of that form."""
        return _literal_between(key, f"{self.prefix}/out/", f"/{kind}")

    def active_anchors(self, instance: str = "*", millis: str = "*", version: str = "*") -> str:
        """The liveliness token announcing an instance's active anchor set (``**`` for all: instance names may
        hold slashes)."""
        if instance == "**":
            return f"{self.prefix}/active/**"
        return f"{self.prefix}/active/{instance}/{millis}/{version}"

    def parse_active_anchors(self, key: str) -> tuple[str, int, str] | None:
        """(instance, accepted_at in ms, version) of an active-anchors token key; None for another key."""
        head = f"{self.prefix}/active/"
        parts = key[len(head) :].split("/") if key.startswith(head) else []
        if len(parts) < 3 or not parts[-2].isdigit():
            return None
        return "/".join(parts[:-2]), int(parts[-2]), parts[-1]

    def member(self, instance: str = "**", fingerprint: str = "", state: str = "", millis: int = 0) -> str:
        """The liveliness token saying which model an instance runs and whether it serves (``**``: all)."""
        if instance == "**":
            return f"{self.prefix}/member/**"
        return f"{self.prefix}/member/{instance}/{fingerprint or NO_FINGERPRINT}/{state}/{millis}"

    def parse_member(self, key: str) -> tuple[str, str, str, int] | None:
        """(instance, fingerprint, state, since in ms) of a member token key; "" for no fingerprint; None for
        another key."""
        head = f"{self.prefix}/member/"
        parts = key[len(head) :].split("/") if key.startswith(head) else []
        if len(parts) < 4 or not parts[-1].isdigit():
            return None
        fingerprint = "" if parts[-3] == NO_FINGERPRINT else parts[-3]
        return "/".join(parts[:-3]), fingerprint, parts[-2], int(parts[-1])

    def instance_of(self, alive_key: str) -> str | None:
        head = f"{self.prefix}/alive/"
        return alive_key[len(head) :] if alive_key.startswith(head) and len(alive_key) > len(head) else None


def _literal_between(key: str, head: str, tail: str) -> str | None:
    """The non-empty part of ``key`` between ``head`` and ``tail``; None if not of that form, or a wildcard."""
    if not (key.startswith(head) and key.endswith(tail)) or len(key) <= len(head) + len(tail):
        return None
    source = key[len(head) : len(key) - len(tail)]
    return source if "*" not in source and "$" not in source else None


def input_key(input_prefix: str, source: str) -> str:
    """Where a robot publishes the images of ``source`` (the service subscribes to ``{input_prefix}/**``)."""
    return f"{input_prefix}/{source}"


def literal_head(key_expr: str) -> str:
    """The chunks of a key expression before its first wildcard: 'robot/*/cam' -> 'robot'."""
    head = []
    for chunk in key_expr.split("/"):
        if "*" in chunk or "$" in chunk:
            break
        head.append(chunk)
    return "/".join(head)


def input_source_of(key: str, head: str) -> str:
    """The source an input key names: the part after ``head`` (an input's literal head); the whole key if
    nothing is left."""
    if head and key.startswith(head + "/"):
        return key[len(head) + 1 :]
    return key
