"""What the fleet must remember, in one store (issue 46, docs/calibration.md): experience pairs, the anchor-set
history, the active set and kept proposals. One interface (``Store``), two backends with one schema: SQLite in
the state dir (the default) and PostgreSQL (a fleet's shared database). Imports only schemas; no zenoh."""

from gcdtrav.service.store.base import Store
from gcdtrav.service.store.opening import open_store, sqlite_file, store_password
from gcdtrav.service.store.records import (
    PAIR_OVERHEAD_BYTES,
    Activation,
    AppendResult,
    Exclusion,
    HistoryRecord,
    PairColumns,
    PairRecord,
    PairTotals,
    SchemaTooNew,
    SourceContents,
    StoredProposal,
    StoreError,
    StoreUnavailable,
    SumsRow,
    concept_key,
    pair_bytes,
)

__all__ = [
    "PAIR_OVERHEAD_BYTES",
    "Activation",
    "AppendResult",
    "Exclusion",
    "HistoryRecord",
    "PairColumns",
    "PairRecord",
    "PairTotals",
    "SchemaTooNew",
    "SourceContents",
    "Store",
    "StoreError",
    "StoreUnavailable",
    "StoredProposal",
    "SumsRow",
    "concept_key",
    "open_store",
    "pair_bytes",
    "sqlite_file",
    "store_password",
]
