"""Bounds on free text and documents from the bus, in one place: whatever a peer sends is checked against them.

Each bound is far above any real use and far below what would cost the service memory or time.
"""

MAX_NAME_CHARS = 200  # an anchor set's name
MAX_CONCEPT_CHARS = 1000  # a concept's text, bounded before its CLIP tokens (at most 75) are counted
MAX_FRAME_ID_CHARS = 256  # a camera frame id (ROS frame ids are short names)
MAX_SOURCE_CHARS = 256  # a source name taken from an input key
MAX_DOCUMENT_DEPTH = 32  # nesting of an anchor-set document: a real one is 3 deep
DEFAULT_MAX_ANCHOR_SET_BYTES = 64 * 1024  # an anchor-set body; 64 anchors in JSON take about 4 kB


def nesting_depth(text: str) -> int:
    """The deepest nesting of [ and { outside quoted strings: bounds a document before a parser recurses."""
    depth = deepest = 0
    quote = ""
    escaped = False
    for char in text:
        if quote:
            if escaped:
                escaped = False
            elif char == "\\" and quote == '"':
                escaped = True
            elif char == quote:
                quote = ""
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(depth - 1, 0)
    return deepest
