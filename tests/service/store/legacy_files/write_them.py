"""How the files here were written: by gcdtrav before the store (commit a055777), its own code, so the import
is tested against what that version really wrote. Rerun (only to change them) with that version importable:

    git archive a055777 | tar -x -C /tmp/old && mkdir -p /tmp/oldpkg/gcdtrav && touch /tmp/oldpkg/gcdtrav/__init__.py
    for p in schemas service client; do ln -s /tmp/old/$p /tmp/oldpkg/gcdtrav/$p; done
    python tests/service/store/legacy_files/write_them.py /tmp/oldpkg

Two concept tuples (an anchor swap between them), three anchor-set versions, 1,250 pairs; the anchor state
and a history of three sets, the last one active."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(old_package_root: str) -> None:
    sys.path.insert(0, old_package_root)
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]  # not this checkout's
    import numpy as np
    from gcdtrav.schemas.anchors import Anchor, AnchorSet
    from gcdtrav.schemas.experience import TraversalOutcome
    from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply
    from gcdtrav.service.experience.store import ExperienceStore
    from gcdtrav.service.runtime.fleet.state import save_anchor_state, write_atomically

    first = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.6)])
    second = AnchorSet(anchors=[Anchor(concept="mud", position=0.2), Anchor(concept="grass", position=0.7)])
    third = AnchorSet(anchors=[Anchor(concept="rock", position=0.0), Anchor(concept="sand", position=0.3),
                               Anchor(concept="asphalt", position=0.9)])  # fmt: skip
    store = ExperienceStore(HERE / "gcdtrav.experience.msgpack", 50_000, 16_000_000, 2.0)
    rng = np.random.default_rng(7)
    for k in range(250):  # 5 cells per outcome
        anchors = (first, second, third)[0 if k < 100 else 1 if k < 180 else 2]
        outcome = TraversalOutcome(stamp=1000.0 + k, x=0.0, y=0.0, score=float(rng.random()), kind="velocity")
        store.add_predicted(rng.random((5, len(anchors))).astype(np.float32), anchors, outcome)
    assert store.save()
    save_anchor_state(HERE / "gcdtrav.anchors.json", third)
    entries = [AnchorHistoryEntry(accepted_at=1700000000.0 + 60 * k, version=s.version, anchor_set=s)
               for k, s in ((2, third), (1, second), (0, first))]  # fmt: skip
    reply = AnchorHistoryReply(instance="old-1", entries=entries)
    write_atomically(HERE / "gcdtrav.anchors-history.json", reply.model_dump_json(indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1])
