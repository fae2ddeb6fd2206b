"""The Conceptual Anchor Set: terrain concepts placed on the traversability scale [0, 1]."""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from gcdtrav.schemas.clip_tokens import MAX_CONCEPT_TOKENS, count_clip_tokens
from gcdtrav.schemas.limits import MAX_CONCEPT_CHARS, MAX_DOCUMENT_DEPTH, MAX_NAME_CHARS
from gcdtrav.schemas.strict import FrozenStrictModel
from pydantic import Field, ValidationError, field_validator, model_validator

MIN_ANCHORS = 2
MAX_ANCHORS = 64


class AnchorSetError(ValueError):
    """An anchor set that cannot be used; ``messages`` lists every problem in words a person can act on."""

    def __init__(self, messages: Sequence[str], source: str | None = None) -> None:
        self.messages = list(messages)
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(where + "invalid anchor set: " + "; ".join(self.messages))


class Anchor(FrozenStrictModel):
    """One concept of the set: its text prompt, its place on the scale and its Gaussian width."""

    concept: str = Field(
        max_length=MAX_CONCEPT_CHARS, description="Text prompt given to the segmentation model, e.g. 'gravel'."
    )
    position: float = Field(description="Traversability of the concept: 0 = untraversable, 1 = ideal ground.")
    width: float | None = Field(
        default=None,
        description="Standard deviation sigma_k of this anchor's Gaussian; None uses the set's default_width.",
    )

    @field_validator("concept")
    @classmethod
    def _concept_is_usable(cls, value: str) -> str:
        text = value.strip()
        if not text:
            raise ValueError("concept must be a non-empty text, e.g. 'gravel'")
        tokens = count_clip_tokens(text)
        if tokens > MAX_CONCEPT_TOKENS:
            raise ValueError(
                f"concept '{text[:40]}...' is {tokens} CLIP tokens long; CLIP reads at most "
                f"{MAX_CONCEPT_TOKENS} (77 with start/end tokens): shorten it"
            )
        return text

    @field_validator("position")
    @classmethod
    def _position_in_unit_interval(cls, value: float) -> float:
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"position {value} is outside [0, 1]; 0 = untraversable, 1 = ideal ground")
        return value

    @field_validator("width")
    @classmethod
    def _width_not_negative(cls, value: float | None) -> float | None:
        if value is not None and not 0.0 <= value < float("inf"):
            raise ValueError(f"width {value} must be a finite number >= 0 (a standard deviation)")
        return value


class AnchorSet(FrozenStrictModel):
    """An ordered Conceptual Anchor Set (CAS) as defined by Häuselmann et al., IFAC 2026."""

    name: str = Field(
        default="custom", max_length=MAX_NAME_CHARS, description="A label for people; not part of the version."
    )
    default_width: float = Field(default=0.0, description="sigma_k of anchors that do not set their own.")
    anchors: list[Anchor]

    @field_validator("default_width")
    @classmethod
    def _default_width_not_negative(cls, value: float) -> float:
        if not 0.0 <= value < float("inf"):
            raise ValueError(f"default_width {value} must be a finite number >= 0")
        return value

    @field_validator("anchors")
    @classmethod
    def _anchor_count(cls, value: list[Anchor]) -> list[Anchor]:
        if not MIN_ANCHORS <= len(value) <= MAX_ANCHORS:
            raise ValueError(
                f"an anchor set needs between {MIN_ANCHORS} and {MAX_ANCHORS} anchors, this one has {len(value)}"
            )
        return value

    @model_validator(mode="after")
    def _ordered_and_unique(self) -> AnchorSet:
        problems = order_and_uniqueness_problems([(a.concept, a.position) for a in self.anchors])
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # ---- derived views -------------------------------------------------------------------------------
    @property
    def concepts(self) -> list[str]:
        return [a.concept for a in self.anchors]

    @property
    def positions(self) -> list[float]:
        return [a.position for a in self.anchors]

    @property
    def widths(self) -> list[float]:
        return [self.default_width if a.width is None else a.width for a in self.anchors]

    def __len__(self) -> int:
        return len(self.anchors)

    @property
    def version(self) -> str:
        """Content hash of what changes results (concepts, positions, effective widths); not the name."""
        canonical = json.dumps(
            [[c, round(p, 9), round(w, 9)] for c, p, w in zip(self.concepts, self.positions, self.widths, strict=True)],
            separators=(",", ":"),
            ensure_ascii=False,
        )
        return hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:16]

    # ---- (de)serialisation ---------------------------------------------------------------------------
    @classmethod
    def parse(cls, data: Any, source: str | None = None) -> AnchorSet:
        """Validate a decoded mapping, raising :class:`AnchorSetError` with readable messages."""
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            messages = _readable_errors(err)
            # Field errors stop pydantic before the set's own checks: run them on what the anchors say.
            set_problems = order_and_uniqueness_problems(_raw_anchors(data))
            messages += [problem for problem in set_problems if not any(problem in m for m in messages)]
            raise AnchorSetError(messages, source) from None

    @classmethod
    def from_text(cls, text: str | bytes, source: str | None = None) -> AnchorSet:
        """Parse JSON or YAML text (JSON is valid YAML), refusing documents nested deeper than a real one."""
        if isinstance(text, bytes):
            try:
                text = text.decode("utf-8")
            except UnicodeDecodeError as err:
                raise AnchorSetError([f"not UTF-8 text: {err}"], source) from None
        try:
            _refuse_deep_nesting(text)
            data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise AnchorSetError([f"not valid JSON or YAML: {err}"], source) from None
        except DocumentTooDeep as err:
            raise AnchorSetError([str(err)], source) from None
        except ValueError as err:  # e.g. an integer of more than 4300 digits (Python's int_max_str_digits)
            raise AnchorSetError([f"not a usable JSON or YAML value: {err}"], source) from None
        if not isinstance(data, dict):
            raise AnchorSetError(
                ['expected a mapping with an \'anchors\' list, e.g. {"anchors": [{"concept": ..., "position": ...}]}'],
                source,
            )
        return cls.parse(data, source)

    @classmethod
    def load(cls, path: str | Path) -> AnchorSet:
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise AnchorSetError([f"cannot read the file: {err}"], str(path)) from None
        return cls.from_text(text, str(path))

    def to_json(self) -> str:
        return self.model_dump_json(indent=2, exclude_none=True)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        if path.suffix.lower() in (".yaml", ".yml"):
            path.write_text(yaml.safe_dump(self.model_dump(exclude_none=True), sort_keys=False), "utf-8")
        else:
            path.write_text(self.to_json() + "\n", "utf-8")


def anchor_diff(active: AnchorSet, new: AnchorSet) -> list[str]:
    """What swapping ``active`` for ``new`` changes, one line per concept: + added, - removed, ~ moved."""
    old = {a.concept: a for a in active.anchors}
    lines = [f"- {c} @ {a.position:.2f}" for c, a in old.items() if c not in set(new.concepts)]
    for anchor in new.anchors:
        before = old.get(anchor.concept)
        width = new.widths[new.concepts.index(anchor.concept)]
        if before is None:
            lines.append(f"+ {anchor.concept} @ {anchor.position:.2f}")
        else:
            old_width = active.widths[active.concepts.index(anchor.concept)]
            if (before.position, old_width) != (anchor.position, width):
                lines.append(
                    f"~ {anchor.concept} @ {before.position:.2f} -> {anchor.position:.2f}"
                    + (f", width {old_width:g} -> {width:g}" if old_width != width else "")
                )
    if active.name != new.name:
        lines.append(f"~ name {active.name!r} -> {new.name!r}")
    return lines


class DocumentTooDeep(ValueError):
    pass


def _refuse_deep_nesting(text: str) -> None:
    """Walk the document's parse events, which PyYAML produces without recursion, and stop at the first
    collection nested deeper than a real anchor set could be, before the recursive composer builds anything.
    Counts flow ([ {) and block (indentation) nesting alike, and sees through quotes and comments."""
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DOCUMENT_DEPTH:
                raise DocumentTooDeep(
                    f"nested more than {MAX_DOCUMENT_DEPTH} levels deep; an anchor set is 3 levels deep"
                )
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def order_and_uniqueness_problems(anchors: Sequence[tuple[str, float | None]]) -> list[str]:
    """The set's own rules on (concept, position) pairs: sorted by position, concepts unique (any case).
    A position of None (unreadable) is left out of the order."""
    problems = []
    placed = [(concept, position) for concept, position in anchors if position is not None]
    for (concept_a, a), (concept_b, b) in itertools.pairwise(placed):
        if b < a:
            problems.append(f"anchors must be sorted by position: '{concept_b}' ({b}) comes after '{concept_a}' ({a})")
    seen: set[str] = set()
    for concept, _ in anchors:
        key = concept.lower()
        if key in seen:
            problems.append(f"concept '{concept}' appears more than once; concepts must be unique")
        seen.add(key)
    return problems


def _raw_anchors(data: Any) -> list[tuple[str, float | None]]:
    """(concept, position) of the anchors a mapping gives, as far as they read (a position outside [0, 1] has
    its own error: None): for the set's own checks when some fields failed."""
    anchors = data.get("anchors") if isinstance(data, dict) else None
    found: list[tuple[str, float | None]] = []
    for anchor in anchors if isinstance(anchors, list) else []:
        concept = anchor.get("concept") if isinstance(anchor, dict) else None
        if isinstance(concept, str) and concept.strip():
            position = anchor.get("position")
            usable = isinstance(position, (int, float)) and not isinstance(position, bool) and 0 <= position <= 1
            found.append((concept.strip(), float(position) if usable else None))
    return found


def _readable_errors(err: ValidationError) -> list[str]:
    messages = []
    for item in err.errors():
        where = ".".join(str(part) for part in item["loc"])
        text = item["msg"].removeprefix("Value error, ")
        if item["type"] == "extra_forbidden":
            text = "unknown field (allowed: name, default_width, anchors; per anchor: concept, position, width)"
        messages.append(f"{where}: {text}" if where else text)
    return messages


PAPER_ANCHORS: tuple[tuple[str, float], ...] = (
    ("water", 0.02),
    ("mud", 0.1),
    ("ice", 0.2),
    ("snow", 0.3),
    ("sand", 0.4),
    ("moss", 0.45),
    ("grass", 0.5),
    ("gravel", 0.6),
    ("soil", 0.65),
    ("dirt", 0.7),
    ("cobblestone", 0.8),
    ("asphalt", 0.98),
    ("concrete", 1.0),
)


def default_anchor_set() -> AnchorSet:
    """The set used in the paper's experiments on GOOSE."""
    return AnchorSet(
        name="paper",
        anchors=[Anchor(concept=c, position=p) for c, p in PAPER_ANCHORS],
    )
