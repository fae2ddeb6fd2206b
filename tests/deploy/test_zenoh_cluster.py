"""The Kubernetes routers as the cluster runs them, on loopback: the rendered router and service configs (TLS,
passwords, access control), the certificate of deploy/kubernetes/tls/make-certificates.sh, and every session
connecting BY THE CLUSTER'S NAMES (gcdtrav-router-N.gcdtrav-router, gcdtrav-router-public).

zenoh's TLS link verifies the server name it takes from the endpoint's host and resolves that host itself
(zenoh-link-tls: get_tls_server_name, then tokio's lookup_host, i.e. getaddrinfo); it has no setting to
connect to an IP under another name. So the sessions run in a child process (zenoh_fleet_by_name.py) whose
resolver is cwrap's nss_wrapper (LD_PRELOAD, Debian libnss-wrapper): NSS_WRAPPER_HOSTS maps the cluster's
names to 127.0.0.1 for that process alone; /etc/hosts and DNS are not touched. Each router listens on its own
loopback port, so the endpoints name a port other than 7447; the names and the certificate are the cluster's.
Routers are zenoh-python sessions in router mode (zenohd is not installed here), as the other tests run them.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from real_components import nss_wrapper
from zenoh_helpers import free_port

ROOT = Path(__file__).resolve().parents[2]
TREE = ROOT / "deploy" / "kubernetes"
MAKE_CERTIFICATES = TREE / "tls" / "make-certificates.sh"
FLEET = Path(__file__).with_name("zenoh_fleet_by_name.py")
NAMES = ["gcdtrav-router-0.gcdtrav-router", "gcdtrav-router-1.gcdtrav-router", "gcdtrav-router-public"]
PASSWORD = "change-me"  # credentials.txt's placeholders, as rendered


def rendered_secret(prefix: str, key: str) -> str:
    if shutil.which("kubectl") is None:
        pytest.skip("kubectl not installed (.ci/run installs it)")
    output = subprocess.run(["kubectl", "kustomize", str(TREE)], capture_output=True, text=True, timeout=60)
    assert output.returncode == 0, output.stderr
    for doc in yaml.safe_load_all(output.stdout):
        if doc and doc["kind"] == "Secret" and doc["metadata"]["name"].startswith(prefix):
            return base64.b64decode(doc["data"][key]).decode()
    raise AssertionError(f"no Secret {prefix}*")


def json5_with(text: str, changes: dict[str, Any]) -> str:
    """The config text with ``changes`` (path -> value) applied, as JSON5 zenoh reads."""
    import zenoh

    config = zenoh.Config.from_json5(text)
    for path, value in changes.items():
        config.insert_json5(path, json.dumps(value))
    return str(config)


class Cluster:
    """Two routers, the service's session and users' sessions, configured from the rendered tree."""

    def __init__(self, folder: Path, certificates: Path) -> None:
        self.folder, self.ca = folder, str(certificates / "ca.crt")
        self.ports = [free_port(), free_port()]
        credentials = folder / "credentials.txt"
        credentials.write_text(rendered_secret("gcdtrav-router-zenoh", "credentials.txt"), "utf-8")
        router = rendered_secret("gcdtrav-router-zenoh", "router.json5")
        self.routers = []
        for index, port in enumerate(self.ports):
            others = [f"tls/{NAMES[i]}:{p}" for i, p in enumerate(self.ports) if i != index]  # the start script
            self.routers.append(
                json5_with(
                    router,
                    {
                        "listen/endpoints": [f"tls/127.0.0.1:{port}"],
                        "connect/endpoints": others,
                        "transport/link/tls/root_ca_certificate": self.ca,
                        "transport/link/tls/listen_private_key": str(certificates / "tls.key"),
                        "transport/link/tls/listen_certificate": str(certificates / "tls.crt"),
                        "transport/auth/usrpwd/dictionary_file": str(credentials),
                    },
                )
            )
        self.service = json5_with(
            rendered_secret("gcdtrav-service-zenoh", "zenoh.json5"),
            {  # the pods' config; router 1 only, so what users put on router 0 must cross the routers' link
                "connect/endpoints": [f"tls/{NAMES[1]}:{self.ports[1]}"],
                "transport/link/tls/root_ca_certificate": self.ca,
            },
        )

    def user(self, name: str, host: str = NAMES[2], router: int = 0) -> str:
        """A robot's, planner's or operator's session: a client of the public address, logged in."""
        return json5_with(
            "{}",
            {
                "mode": "client",
                "connect/endpoints": [f"tls/{host}:{self.ports[router]}"],
                "scouting/multicast/enabled": False,
                "transport/link/tls/root_ca_certificate": self.ca,
                "transport/link/tls/verify_name_on_connect": True,
                "transport/auth/usrpwd/user": name,
                "transport/auth/usrpwd/password": PASSWORD,
            },
        )

    def run(self, users: dict[str, str], puts: list[tuple[str, str]], timeout_s: float) -> dict[str, list[str]]:
        """The keys of ``puts`` that reached the service's subscriber (on **), and the sessions refused."""
        spec = self.folder / "spec.json"
        spec.write_text(
            json.dumps(
                {
                    "routers": self.routers,
                    "service": self.service,
                    "users": users,
                    "puts": puts,
                    "subscribe": "**",
                    "timeout_s": timeout_s,
                }
            ),
            "utf-8",
        )
        hosts = self.folder / "hosts"
        hosts.write_text("".join(f"127.0.0.1 {name}\n" for name in NAMES), "utf-8")
        environ = {**os.environ, "LD_PRELOAD": str(nss_wrapper()), "NSS_WRAPPER_HOSTS": str(hosts)}
        done = subprocess.run(
            [sys.executable, str(FLEET), str(spec)], capture_output=True, text=True, env=environ, timeout=120
        )
        assert done.returncode == 0, done.stdout + done.stderr
        return json.loads(done.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def certificates(folder: Path, *extra: str, subject_alt_names: str | None = None) -> Path:
    """The recipe's certificate (make-certificates.sh); ``subject_alt_names``: an openssl-made one instead."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command (.ci/run installs it)")
    out = folder / "tls"
    if subject_alt_names is None:
        subprocess.run(["sh", str(MAKE_CERTIFICATES), str(out), *extra], check=True, capture_output=True, timeout=60)
        return out
    out.mkdir()
    (out / "san.cnf").write_text(f"subjectAltName={subject_alt_names}\n", "utf-8")
    for args in (
        ["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=ca", "-keyout", "ca.key"],
        ["req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=gcdtrav-router", "-keyout", "tls.key"],
    ):
        subprocess.run(
            ["openssl", *args, "-out", "ca.crt" if "-x509" in args else "tls.csr"], check=True, cwd=out, timeout=60
        )
    sign = ["x509", "-req", "-in", "tls.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial", "-days", "2"]
    subprocess.run(
        ["openssl", *sign, "-extfile", "san.cnf", "-out", "tls.crt"],
        check=True,
        capture_output=True,
        cwd=out,
        timeout=60,
    )
    return out


ROBOT_FRAME, ROBOT_CMD = "gcdtrav/in/r1/front", "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_abc"


def test_the_recipes_certificate_connects_the_service_and_a_second_router_by_the_cluster_names(
    tmp_path: Path,
) -> None:
    """A robot on router 0 by the public name, the service on router 1 by its pod name, the routers to each
    other by pod name: the robot's frame crosses both TLS links and reaches the service."""
    cluster = Cluster(tmp_path, certificates(tmp_path, "zenoh.example.com"))
    outcome = cluster.run({"robot": cluster.user("robot")}, [("robot", ROBOT_FRAME)], timeout_s=30)
    assert outcome == {"seen": [ROBOT_FRAME], "refused": []}


def test_a_wildcard_over_one_label_is_refused_so_nothing_connects(tmp_path: Path) -> None:
    """The recipe before: DNS:*.gcdtrav-router. rustls (zenoh's TLS) refuses the pod names under it."""
    wildcard = "DNS:*.gcdtrav-router,DNS:gcdtrav-router-public"
    cluster = Cluster(tmp_path, certificates(tmp_path, subject_alt_names=wildcard))
    outcome = cluster.run({"robot": cluster.user("robot")}, [("robot", ROBOT_FRAME)], timeout_s=5)
    # The robot reaches router 0 by the public name, spelt out; the service cannot reach router 1 by its pod
    # name, nor router 0 router 1: the frame goes nowhere.
    assert outcome == {"seen": [], "refused": ["service"]}


def test_each_user_sends_exactly_what_the_docs_ask_of_it(tmp_path: Path) -> None:
    """The routers' access control, for real: robots put frames and their cmd_vel/odom; planners only planned
    paths; operators only answers; no planner or operator reaches a robot's cmd_vel or odom, or forges a map."""
    cluster = Cluster(tmp_path, certificates(tmp_path))
    allowed = {
        ("robot", ROBOT_FRAME),
        ("robot", "gcdtrav/in/r1/front/outcome"),
        ("robot", ROBOT_CMD),
        ("robot", "0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_abc"),
        ("robot", "gcdtrav/relay/r1/front/health"),
        ("planner", "gcdtrav/in/r1/front/planned_path"),
        ("operator", "gcdtrav/in/r1/front/answer"),
    }
    refused = {
        ("planner", "gcdtrav/in/intruder/cam"),  # a planner inventing a source
        ("planner", "gcdtrav/in/r1/front/answer"),
        ("planner", "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_abc"),  # driving someone's robot
        ("operator", "gcdtrav/in/intruder/cam"),
        ("operator", "0/r2/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_abc"),
        ("operator", "0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_operator"),
        ("robot", "gcdtrav/out/r2/front/maps"),  # a forged map
        ("planner", "gcdtrav/out/r2/front/maps"),
    }
    users = {name: cluster.user(name) for name in ("robot", "planner", "operator")}
    outcome = cluster.run(users, sorted(allowed | refused), timeout_s=30)
    seen, expected = set(outcome["seen"]), {key for _, key in allowed}
    assert outcome["refused"] == [] and seen == expected, (seen - expected, expected - seen)
