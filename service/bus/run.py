"""`gcdtrav serve`: build the pipeline, open the session, run until SIGINT/SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType

import zenoh
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.cpus import usable_cpus
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.state import load_anchor_state

log = logging.getLogger("gcdtrav.service")


def starting_anchor_set(settings: ServiceSettings) -> AnchorSet:
    """The last set accepted at runtime wins over the configured file, which wins over the paper's set."""
    persisted = load_anchor_state(settings.state_file)
    if persisted is not None:
        log.info(
            "anchor set %s from the state file %s (delete it to use the configured set)",
            persisted.version,
            settings.state_file,
        )
        return persisted
    if settings.anchors_file is not None:
        return AnchorSet.load(settings.anchors_file)
    return default_anchor_set()


def build_service_pipeline(settings: ServiceSettings) -> Pipeline:

    import torch
    from gcdtrav.service.pipeline import clipseg_pipeline

    if settings.threads is not None:
        torch.set_num_threads(settings.threads)
    anchors = starting_anchor_set(settings)
    return clipseg_pipeline(settings.model, settings.precision, anchors, settings.engine, settings.state_dir / "models")


def with_torch_threads(settings: ServiceSettings) -> ServiceSettings:
    """``threads`` made explicit: as configured, else torch's default capped by the CPUs really usable."""
    import torch

    if settings.threads is not None:
        return settings
    threads = min(torch.get_num_threads(), usable_cpus())
    log.info("torch threads: %d (CPUs usable by this process: %d)", threads, usable_cpus())
    return settings.model_copy(update={"threads": threads})


def run_service(settings: ServiceSettings, config: zenoh.Config) -> int:
    from gcdtrav.service.bus.node import TraversabilityService

    settings = with_torch_threads(settings)
    pipeline = build_service_pipeline(settings)
    stop = threading.Event()

    def request_stop(signum: int, _frame: FrameType | None) -> None:
        log.info("%s received: finishing the frame in flight and shutting down", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    zenoh.init_log_from_env_or("error")
    try:
        session = zenoh.open(config)
    except zenoh.ZError as err:
        raise SettingsError(f"cannot open the zenoh session: {err}") from None
    try:
        service = TraversabilityService(session, pipeline, settings)
    except SettingsError:
        session.close()
        raise
    try:
        service.start()
        while not stop.wait(0.5):
            pass
    finally:
        service.stop()
        session.close()
    log.info("stopped")
    return 0
