"""`gcdtrav serve`: build the pipeline, open the session, run until SIGINT/SIGTERM."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from types import FrameType
from typing import TYPE_CHECKING, NoReturn

import numpy as np
import zenoh
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.backends.cpus import set_torch_threads, usable_cpus
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.http_endpoints import Checks, HttpEndpoints
from gcdtrav.service.store import Store, StoreError, StoreUnavailable
from gcdtrav.service.store.opening import service_store

if TYPE_CHECKING:
    from gcdtrav.service.bus.node import TraversabilityService

log = logging.getLogger("gcdtrav.service")
MEASUREMENT_STOP_S = 5.0  # at shutdown, how long a background measurement may take to reach its next mode
# Before joining the fleet, watch the inputs this long: robots at 2 Hz or faster are then established in this
# instance's table as in the others', so no source is left to neither when the sources move (assignment.py).
JOIN_OBSERVE_S = 1.0
WARM_UP_SIDE = 64  # the warm-up frame; the backend resizes every image to its input size anyway


def starting_anchor_set(settings: ServiceSettings, store: Store | None) -> AnchorSet:
    """The fleet's active set (the store is its record, an old state file imported into it at its first open)
    wins over the configured file, which wins over the paper's set. The pipeline starts with it, so a restart computes
    the text embeddings once; the anchor switch still reads the store again (it may have changed meanwhile).
    ``store``: the store opened at start (``store_at_start``); None while it is not reached (not tried again
    here: the anchor switch installs its set once it answers)."""
    active = None if store is None else active_set_of(store)
    if active is not None:
        log.info("anchor set %s: the store's active set", active.version)
        return active
    if settings.anchors_file is not None:
        return AnchorSet.load(settings.anchors_file)
    return default_anchor_set()


def store_at_start(settings: ServiceSettings) -> Store | None:
    """The store, opened once, before the model loads, with a gcdtrav's files from before the store imported
    into it (service/store/legacy.py: the old anchor state is read there, once): its active set is the
    pipeline's first and the service takes it over. None while it cannot be reached (the service starts with
    the configured set, its outbox keeps trying and imports the files at its first open). Refused (a newer
    schema, an unreadable password_file, psycopg missing): SettingsError, so ``gcdtrav serve`` exits 2 before
    it loads the model."""
    try:
        return service_store(settings)
    except StoreUnavailable as err:
        log.warning("store not reached at start (serving meanwhile; retried): %s", err)
        return None
    except StoreError as err:
        raise SettingsError(str(err)) from None


def active_set_of(store: Store) -> AnchorSet | None:
    """The store's active set; None for an empty store or one that cannot be read now (the service then starts
    with the configured set, and the anchor switch installs the store's once it answers)."""
    try:
        active = store.active()
    except StoreError as err:
        log.warning("anchor store not read at start: %s", err)
        return None
    return None if active is None else active.anchor_set


def build_service_pipeline(settings: ServiceSettings, store: Store | None) -> Pipeline:
    """The model in the mode to serve with: ``precision: auto`` with no measurement cached for this machine
    serves fp32 at once (``run_service`` then measures in the background), unless measure_before_serving."""
    from gcdtrav.service.pipeline import clipseg_pipeline

    set_torch_threads(settings.threads)
    anchors = starting_anchor_set(settings, store)
    return clipseg_pipeline(
        settings.model,
        settings.precision,
        anchors,
        settings.engine,
        settings.cache_dir,
        measure_now=settings.measure_before_serving,
    )


def with_torch_threads(settings: ServiceSettings) -> ServiceSettings:
    """``threads`` made explicit: as configured, else torch's default capped by the CPUs really usable."""
    if settings.threads is not None:
        return settings
    threads = set_torch_threads(None)
    log.info("torch threads: %d (CPUs usable by this process: %d)", threads, usable_cpus())
    return settings.model_copy(update={"threads": threads})


def warm_up(pipeline: Pipeline) -> None:
    """One inference before the instance joins: the first call of a backend pays its lazy set-up (kernel
    choice, allocations), which the first robot it takes over would otherwise wait for."""
    began = time.perf_counter()
    pipeline.process(np.full((WARM_UP_SIDE, WARM_UP_SIDE, 3), 128, np.uint8))
    log.info("warmed up: one inference in %.0f ms before joining the fleet", (time.perf_counter() - began) * 1e3)


def open_session(config: zenoh.Config, fallback: zenoh.Config | None = None) -> zenoh.Session:
    """The session; if it cannot open (serve's default port taken), the fallback config's, with a warning."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as err:
        if fallback is None:
            raise SettingsError(f"cannot open the zenoh session: {err}") from None
        log.warning(
            "cannot listen on serve's default endpoint (%s): listening on a port zenoh picks instead; "
            "give -l ENDPOINT to choose one",
            str(err).strip().splitlines()[0][:200] if str(err).strip() else type(err).__name__,
        )
    try:
        return zenoh.open(fallback)
    except zenoh.ZError as err:
        raise SettingsError(f"cannot open the zenoh session: {err}") from None


def run_service(settings: ServiceSettings, config: zenoh.Config, fallback: zenoh.Config | None = None) -> NoReturn:
    """Serve until SIGINT/SIGTERM, then exit the process (``exit_now``). ``fallback``: the zenoh config to use if
    ``config`` cannot open. The HTTP endpoints open first (a taken port: SettingsError, exit 2, before the model
    loads): the probes answer 503 "starting" while the model loads, measures and warms up."""
    http = HttpEndpoints(settings)
    try:
        code = serve_with(http, settings, config, fallback)
    finally:
        http.close()
    exit_now(code)


def serve_with(
    http: HttpEndpoints, settings: ServiceSettings, config: zenoh.Config, fallback: zenoh.Config | None
) -> int:
    settings = with_torch_threads(settings)
    store = store_at_start(settings)
    try:
        service, session, pipeline = start_serving(http, settings, config, fallback, store)
    except BaseException:
        if store is not None:  # not handed over yet: the service closes it once it has it
            store.close()
        raise
    stop = threading.Event()

    def request_stop(signum: int, _frame: FrameType | None) -> None:
        log.info("%s received: finishing the frame in flight and shutting down", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    http.serve(Checks(service.liveness, service.readiness, service.metrics.registry))
    measurement = None
    try:
        service.start(observe_s=JOIN_OBSERVE_S)
        if pipeline.describe().needs_measurement:  # status answers meanwhile: measuring
            from gcdtrav.service.backends.precision_choice import measure_in_background

            measurement = measure_in_background(pipeline.backend)
        while not stop.wait(0.5):
            pass
    finally:
        deadline = time.monotonic() + settings.shutdown_grace_s  # the whole exit, within the grace period
        service.stop()
        session.close()
    log.info("stopped")
    left_s = min(MEASUREMENT_STOP_S, max(0.0, deadline - time.monotonic()))
    if measurement is not None and not measurement.stop(left_s):  # exit_now does not wait for it
        log.info("the measurement of the modes is inside an export: not waiting for it (nothing cached)")
    return 0


def start_serving(
    http: HttpEndpoints,
    settings: ServiceSettings,
    config: zenoh.Config,
    fallback: zenoh.Config | None,
    store: Store | None,
) -> tuple[TraversabilityService, zenoh.Session, Pipeline]:
    """The model loaded and warmed up, the session open, the service built on them (not started)."""
    from gcdtrav.service.bus.node import TraversabilityService

    if settings.measure_before_serving and settings.precision == "auto":
        http.starting("loading the model and measuring the modes (precision auto, measure_before_serving)")
    pipeline = build_service_pipeline(settings, store)
    http.starting("warming up")
    warm_up(pipeline)
    zenoh.init_log_from_env_or("error")
    http.starting("opening the zenoh session")
    session = open_session(config, fallback)
    try:
        return TraversabilityService(session, pipeline, settings, store), session, pipeline
    except BaseException:
        session.close()
        raise


def exit_now(code: int) -> NoReturn:
    """Exit the process with ``code`` once everything is stopped, closed and logged, without the interpreter's
    teardown: torch's alone takes 0.5 s, the whole service's 1.1 s on an idle 2-core box and about 10 s on a
    loaded one, which would outlast ``shutdown_grace_s`` (Kubernetes then kills the pod). A background
    measurement may also be inside native code (an ONNX export, a quantisation) that cannot be interrupted,
    around which the interpreter's exit aborts ('terminate called without an active exception')."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
