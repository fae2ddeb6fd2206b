"""The deploy/ access-control and TLS examples, tested for real on loopback."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import zenoh
from conftest import textured_image
from zenoh_helpers import free_port, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import QueryTimeout, TraversabilityClient
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"
NEW_SET = {"anchors": [{"concept": "puddle", "position": 0.0}, {"concept": "road", "position": 1.0}]}


def start(backend, config: zenoh.Config, state_dir: Path) -> tuple[TraversabilityService, zenoh.Session]:  # type: ignore[no-untyped-def]
    session = zenoh.open(config)
    service = TraversabilityService(
        session,
        Pipeline(backend, default_anchor_set(), EngineSettings()),
        ServiceSettings(state_dir=state_dir, instance="secure"),
    )
    service.start()
    return service, session


def user_config(port: int, user: str | None, password: str | None) -> zenoh.Config:
    config = zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    if user is not None:
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return config


def test_only_the_operator_can_change_the_anchor_set(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    port = free_port()
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("robot:robot-secret\nplanner:planner-secret\noperator:operator-secret\n")
    config = zenoh.Config.from_file(DEPLOY / "access-control.json5")
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    service, session = start(tiny_backend, config, tmp_path)
    try:
        with TraversabilityClient(config=user_config(port, "robot", "robot-secret"), timeout=1.5) as robot:
            assert wait_until(lambda: service_reachable(robot), 60)  # status and maps are open to robots
            with pytest.raises(QueryTimeout):  # the service session's ACL drops the query: no reply at all
                robot.set_anchors(NEW_SET)
            assert service.pipeline.anchors.version == default_anchor_set().version
        with TraversabilityClient(config=user_config(port, "operator", "operator-secret"), timeout=5.0) as operator:
            assert wait_until(lambda: service_reachable(operator), 60)
            version = operator.set_anchors(NEW_SET)
            assert service.pipeline.anchors.version == version != default_anchor_set().version
        for user, password in ((None, None), ("robot", "wrong")):  # no session without valid credentials
            with TraversabilityClient(config=user_config(port, user, password), timeout=1.0) as stranger:
                time.sleep(0.5)
                assert not service_reachable(stranger)
    finally:
        service.stop()
        session.close()


def test_only_robots_can_put_frames(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    port = free_port()
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("robot:robot-secret\nplanner:planner-secret\n")
    config = zenoh.Config.from_file(DEPLOY / "access-control.json5")
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    service, session = start(tiny_backend, config, tmp_path)
    try:
        with (
            TraversabilityClient(config=user_config(port, "planner", "planner-secret"), timeout=5.0) as planner,
            TraversabilityClient(config=user_config(port, "robot", "robot-secret"), timeout=5.0) as robot,
        ):
            assert wait_until(lambda: service_reachable(planner) and service_reachable(robot), 60)
            for _ in range(3):
                planner.publish_image("intruder/cam", textured_image(48, 64))
            # the service's input subscription known to the robot's session: its one frame is sent
            assert subscribed_elsewhere(robot.session, input_key(robot.input_prefix, "r1/cam"))
            robot.publish_image("r1/cam", textured_image(48, 64))
            assert wait_until(lambda: "r1/cam" in robot.status().sources, 60)
            planner.publish_image("intruder/cam", textured_image(48, 64))
            time.sleep(0.5)
            status = robot.status()
            assert list(status.sources) == ["r1/cam"] and status.rejected_by_reason == {}  # never reached it
    finally:
        service.stop()
        session.close()


def make_certificates(folder: Path) -> None:
    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=folder, timeout=60)

    openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-subj",
        "/CN=gcdtrav-test-ca",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
    )
    (folder / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in ("service", "operator"):
        openssl(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            f"/CN={name}",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
        )
        openssl(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "2",
            "-extfile",
            "san.cnf",
            "-out",
            f"{name}.pem",
        )


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command (.ci/run installs it)")
def test_tls_example_with_mutual_authentication(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    make_certificates(tmp_path)
    port = free_port()
    config = zenoh.Config.from_file(DEPLOY / "tls.json5")
    config.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    for field, name in {
        "root_ca_certificate": "ca.pem",
        "listen_private_key": "service.key",
        "listen_certificate": "service.pem",
        "connect_private_key": "service.key",
        "connect_certificate": "service.pem",
    }.items():
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(str(tmp_path / name)))
    service, session = start(tiny_backend, config, tmp_path / "state")

    def tls_client(with_certificate: bool) -> zenoh.Config:
        client = zenoh_config(mode="peer", connect=[f"tls/127.0.0.1:{port}"], multicast_scouting=False)
        client.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "ca.pem")))
        if with_certificate:
            client.insert_json5("transport/link/tls/enable_mtls", "true")
            client.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(tmp_path / "operator.key")))
            client.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(tmp_path / "operator.pem")))
        return client

    try:
        with TraversabilityClient(config=tls_client(True), timeout=2.0) as trusted:
            assert wait_until(lambda: service_reachable(trusted), 60)
            assert trusted.status().instance == "secure"
        with TraversabilityClient(config=tls_client(False), timeout=1.0) as anonymous:
            time.sleep(0.5)
            assert not service_reachable(anonymous)  # mutual TLS: no client certificate, no link
    finally:
        service.stop()
        session.close()
