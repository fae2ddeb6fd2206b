"""Which live instances may take sources, by the model they run. No middleware here.

Every instance advertises its model's fingerprint (``BackendDescription.fingerprint``: a hash of the
checkpoint's config and weight files) and a state, with when it entered that state, in a liveliness token
(``Keys.member``). From the same tokens every instance decides the same thing, with no coordinator:

* The fleet's model is the model of the *reference*: the earliest ``serving`` instance (its ``since``
  stamp, then its name); when none serves, the earliest ``mixed`` one; when none either, the earliest
  ``held`` one (the instances of a model that was refused resume when the last of the serving model leaves).
  An instance already serving therefore keeps the fleet: a newcomer, or several newcomers at once, never
  take it over by numbers. Two instances started at the same moment are ordered by their stamps.
* An instance whose fingerprint differs from the fleet's takes no sources (it is *refused*), unless it
  advertises ``mixed`` (``allow_mixed_models``: a model upgrade, docs/deploy/README.md). It advertises
  ``held`` until the fleet's model is its own.
* An instance with no fingerprint (a backend that has none) is never refused and never the reference.
* While any live instance advertises no member token (an instance before 1.4, which cannot apply this
  rule), no one is refused: every instance must compute the same table, and the older one counts everyone.

A new instance advertises ``held`` until its first decision, so a clock running behind on its box cannot
make it the reference of a fleet that already serves.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

SERVING, HELD, MIXED = "serving", "held", "mixed"


@dataclass(frozen=True)
class Member:
    """What one instance advertises: its model's fingerprint ("" unknown), its state, since when (ms)."""

    instance: str
    fingerprint: str
    state: str
    since_ms: int

    @property
    def order(self) -> tuple[int, str]:
        return self.since_ms, self.instance


@dataclass(frozen=True)
class FleetView:
    """The decision for a set of live instances: who is refused and why, and the fleet's model."""

    refused: Mapping[str, str]  # instance -> why it takes no sources
    reference: Member | None  # the instance whose model is the fleet's; None: no fingerprint known
    suspended: str = ""  # why the rule is not applied now ("" when it is)

    def eligible(self, live: Iterable[str]) -> set[str]:
        return {name for name in live if name not in self.refused}


@dataclass(frozen=True)
class FleetModelsStatus:
    """What the status says of the models: why this instance is refused ("" if not), everyone's fingerprint."""

    refused: str
    fingerprints: Mapping[str, str]


def reference_of(members: Iterable[Member]) -> Member | None:
    """The instance whose model is the fleet's (module docstring); only fingerprinted members count."""
    known = [m for m in members if m.fingerprint]
    for state in (SERVING, MIXED, HELD):
        candidates = [m for m in known if m.state == state]
        if candidates:
            return min(candidates, key=lambda m: m.order)
    return None


def decide(live: Iterable[str], members: Mapping[str, Member]) -> FleetView:
    """Who of ``live`` is refused, from the member tokens of the live instances."""
    live = set(live)
    unadvertised = sorted(live - set(members))
    present = [members[name] for name in live if name in members]
    reference = reference_of(present)
    if unadvertised:
        why = f"{', '.join(unadvertised)} advertises no model (before 1.4): no instance is refused"
        return FleetView({}, reference, why)
    if reference is None:
        return FleetView({}, None)
    refused = {
        m.instance: refusal(m, reference)
        for m in present
        if m.fingerprint and m.fingerprint != reference.fingerprint and m.state != MIXED
    }
    return FleetView(refused, reference)


def refusal(member: Member, reference: Member) -> str:
    return (
        f"model {member.fingerprint} differs from the fleet's {reference.fingerprint} (instance "
        f"{reference.instance}, {reference.state}): takes no sources; allow_mixed_models: true shares them "
        "during a model upgrade (docs/deploy README, 'Upgrading the model')"
    )


def own_state(instance: str, view: FleetView, allow_mixed: bool) -> str:
    """The state this instance should advertise after ``view``."""
    if allow_mixed:
        return MIXED
    return HELD if instance in view.refused else SERVING
