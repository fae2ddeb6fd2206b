"""Each robot its own identity, on a real router (issue 58): the shipped router config (router.json5) in router
mode with the recipe's certificate, the identity endpoint (mTLS) and the access control `gcdtrav identity`
generates; robots r7 and r8 connect with the certificates and session configs it issued.

Each test also runs its attack against the role ACL shipped before (every robot logs in as "robot"): where
that one lets the attack through, the check is shown to catch something.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import shlex
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import torch_free_gcdtrav
from gcdtrav.client.commands import identity
from zenoh_helpers import free_port, wait_until

ROOT = Path(__file__).resolve().parents[2]
ZENOH = ROOT / "deploy" / "kubernetes" / "base" / "zenoh"
MAKE_CERTIFICATES = ROOT / "deploy" / "kubernetes" / "tls" / "make-certificates.sh"
PASSWORD = "change-me"  # credentials.txt's placeholder
PROBES = itertools.count()


def gcdtrav_identity(*arguments: str) -> int:
    parser = argparse.ArgumentParser()
    identity.add_identity_command(parser.add_subparsers(dest="command"))
    return identity.run(parser.parse_args(["identity", *arguments]))


class Fleet:
    """One router as the cluster runs it, the service's trusted session, and identities issued by the command."""

    def __init__(self, folder: Path, per_identity: bool) -> None:
        if shutil.which("openssl") is None:
            pytest.skip("needs the openssl command (.ci/run installs it)")
        self.folder, self.tls = folder, folder / "tls"
        subprocess.run(["sh", str(MAKE_CERTIFICATES), str(self.tls), "IP:127.0.0.1"], check=True, capture_output=True)
        self.internal, self.identity_port = free_port(), free_port()
        self.per_identity = per_identity
        self.stack = ExitStack()

    def issue(self, role: str, name: str, valid_hours: float = 24.0) -> None:
        endpoint = f"tls/127.0.0.1:{self.identity_port}"
        assert (
            gcdtrav_identity(
                "add", str(self.tls), role, name, "--valid-hours", str(valid_hours), "--endpoint", endpoint
            )
            == 0
        )

    def router(self) -> zenoh.Session:
        config = zenoh.Config.from_json5((ZENOH / "router.json5").read_text("utf-8"))
        mtls = f"tls/127.0.0.1:{self.identity_port}#enable_mtls=true;close_link_on_expiration=true"
        changes: dict[str, Any] = {
            "listen/endpoints": [f"tls/127.0.0.1:{self.internal}", mtls],
            "transport/link/tls/root_ca_certificate": str(self.tls / "ca.crt"),
            "transport/link/tls/listen_private_key": str(self.tls / "tls.key"),
            "transport/link/tls/listen_certificate": str(self.tls / "tls.crt"),
            "transport/auth/usrpwd/dictionary_file": str(ZENOH / "credentials.txt"),
        }
        for path, value in changes.items():
            config.insert_json5(path, json.dumps(value))
        if self.per_identity:  # what the router's start command adds: zenohd --cfg access_control:<file>
            config.insert_json5("access_control", (self.tls / "access-control.json5").read_text("utf-8"))
        return self.open(config)

    def trusted(self) -> zenoh.Session:
        return self.open(self.password_config("gcdtrav-service"))

    def user(self, role: str, name: str) -> zenoh.Session:
        """The identity's session from the config the command wrote (per identity), or its role's password."""
        if not self.per_identity:
            return self.open(self.password_config(role))
        issued = self.tls / "identities"
        config = zenoh.Config.from_json5((issued / f"{role}-{name}.json5").read_text("utf-8"))
        for file in ("root_ca_certificate", "connect_certificate", "connect_private_key"):  # relative: as copied
            relative = json.loads(config.get_json(f"transport/link/tls/{file}"))
            where = self.tls if relative == "ca.crt" else issued
            config.insert_json5(f"transport/link/tls/{file}", json.dumps(str(where / relative)))
        return self.open(config)

    def password_config(self, user: str) -> zenoh.Config:
        config = zenoh.Config()
        for path, value in {
            "mode": "client",
            "connect/endpoints": [f"tls/127.0.0.1:{self.internal}"],
            "scouting/multicast/enabled": False,
            "transport/link/tls/root_ca_certificate": str(self.tls / "ca.crt"),
            "transport/auth/usrpwd/user": user,
            "transport/auth/usrpwd/password": PASSWORD,
        }.items():
            config.insert_json5(path, json.dumps(value))
        return config

    def open(self, config: zenoh.Config) -> zenoh.Session:
        config.insert_json5("transport/shared_memory/enabled", "false")
        return self.stack.enter_context(zenoh.open(config))


@contextmanager
def fleet(tmp_path: Path, per_identity: bool) -> Iterator[Fleet]:
    built = Fleet(tmp_path, per_identity)
    for role, name in (("robot", "r7"), ("robot", "r8"), ("operator", "alice")):
        built.issue(role, name)
    with built.stack:
        built.router()
        yield built


def heard(session: zenoh.Session, key_expr: str) -> list[str]:
    keys: list[str] = []
    session.declare_subscriber(key_expr, lambda sample: keys.append(str(sample.key_expr)))
    return keys


def put_then_probe(sender: zenoh.Session, forbidden: str, allowed_under: str, keys: list[str]) -> bool:
    """Whether ``forbidden`` arrived: put first, then a fresh key under ``allowed_under`` (the same path, in
    order) until that one is heard."""
    allowed = f"{allowed_under}/{next(PROBES)}"
    wait_until(lambda: (sender.put(forbidden, b"x"), sender.put(allowed, b"x"), allowed in keys)[-1], timeout=15)
    assert allowed in keys, f"{allowed} never arrived: the check cannot tell"
    return forbidden in keys


@pytest.mark.parametrize("per_identity", [True, False], ids=["per-identity", "role-acl-before"])
def test_a_robot_puts_only_under_its_own_keys(tmp_path: Path, per_identity: bool) -> None:
    with fleet(tmp_path, per_identity) as built:
        service, r7 = built.trusted(), built.user("robot", "r7")
        keys = heard(service, "**")
        forged = {
            "gcdtrav/in/r8/front/outcome",  # invented outcomes in r8's name: they would teach the fleet
            "gcdtrav/in/r8/front",  # frames as r8: blinds r8's grid
            "0/r8/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_abc",  # steering r8
            "gcdtrav/relay/r8/front/health",
        }
        arrived = {key for key in sorted(forged) if put_then_probe(r7, key, "gcdtrav/in/r7/probe", keys)}
        assert arrived == (set() if per_identity else forged)
        assert put_then_probe(r7, "0/r7/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_a", "gcdtrav/relay/r7/probe", keys)


@pytest.mark.parametrize("per_identity", [True, False], ids=["per-identity", "role-acl-before"])
def test_a_robot_reads_only_its_own_maps(tmp_path: Path, per_identity: bool) -> None:
    with fleet(tmp_path, per_identity) as built:
        service, r7 = built.trusted(), built.user("robot", "r7")
        everything, r8_maps = heard(r7, "gcdtrav/**"), heard(r7, "gcdtrav/out/r8/front/maps")
        own = heard(r7, "gcdtrav/out/r7/**")
        for _ in range(2):
            service.put("gcdtrav/out/r8/front/maps", b"r8's map")
        assert put_then_probe(service, "gcdtrav/out/r8/front/grid", "gcdtrav/out/r7/front", own) is False
        time.sleep(0.3)
        leaked = r8_maps + [key for key in everything if "/r8/" in key]
        assert (leaked == []) == per_identity, leaked


@pytest.mark.parametrize("per_identity", [True, False], ids=["per-identity", "role-acl-before"])
def test_a_robot_declares_no_queryable_or_token_outside_its_keys(tmp_path: Path, per_identity: bool) -> None:
    with fleet(tmp_path, per_identity) as built:
        service, r7 = built.trusted(), built.user("robot", "r7")
        r7.declare_queryable("gcdtrav/in/r8/front/answer", lambda query: query.reply(query.key_expr, b"r7 answers"))
        own_token = "@ros2_lv/0/aa/0/1/MP/%/%r7/node"  # its own ROS graph token (namespace /r7)
        held = [r7.liveliness().declare_token(key) for key in ("robots/r8/present", own_token)]
        time.sleep(1.0)
        replies = [r for r in service.get("gcdtrav/in/r8/front/answer", timeout=2.0) if r.ok is not None]
        tokens = {
            str(reply.ok.key_expr)
            for expression in ("robots/**", "@ros2_lv/**")
            for reply in service.liveliness().get(expression, timeout=2.0)
            if reply.ok is not None
        }
        assert len(held) == 2
        assert own_token in tokens
        assert (replies == [] and "robots/r8/present" not in tokens) == per_identity, (replies, tokens)


@pytest.mark.parametrize("per_identity", [True, False], ids=["per-identity", "role-acl-before"])
def test_only_an_operator_queries_the_anchor_set(tmp_path: Path, per_identity: bool) -> None:
    with fleet(tmp_path, per_identity) as built:
        service = built.trusted()
        service.declare_queryable("gcdtrav/config/anchors", lambda query: query.reply(query.key_expr, b"set"))
        r7, alice = built.user("robot", "r7"), built.user("operator", "alice")
        time.sleep(1.0)
        answered = {
            who: any(r.ok is not None for r in session.get("gcdtrav/config/anchors", timeout=2.0))
            for who, session in (("r7", r7), ("alice", alice))
        }
        assert answered == {"r7": False, "alice": True}  # the role ACL already refused robots this


def test_a_revoked_robot_is_refused_when_its_certificate_expires_and_the_others_keep_working(tmp_path: Path) -> None:
    """Revoking r7 (no renewal) while it drives: the router closes its link when the short-lived certificate
    expires and refuses it from then on; r8 is never interrupted. The router is not restarted."""
    built = Fleet(tmp_path, per_identity=True)
    lifetime_s = 12.0
    built.issue("robot", "r7", valid_hours=lifetime_s / 3600)
    expires = time.time() + lifetime_s
    built.issue("robot", "r8")
    with built.stack:
        built.router()
        service = built.trusted()
        arrivals: dict[str, list[float]] = {"r7": [], "r8": []}
        service.declare_subscriber(
            "gcdtrav/in/*/front", lambda sample: arrivals[str(sample.key_expr).split("/")[2]].append(time.time())
        )
        r7, r8 = built.user("robot", "r7"), built.user("robot", "r8")
        assert gcdtrav_identity("revoke", str(built.tls), "robot", "r7") == 0  # the rollout never comes here
        while time.time() < expires + 6.0:
            r7.put("gcdtrav/in/r7/front", b"frame")
            r8.put("gcdtrav/in/r8/front", b"frame")
            time.sleep(0.2)
    assert arrivals["r7"] and arrivals["r7"][-1] <= expires + 1.5, (arrivals["r7"][-1:], expires)
    assert arrivals["r7"][0] < expires - lifetime_s / 2  # it worked until then
    gaps = [b - a for a, b in zip(arrivals["r8"], arrivals["r8"][1:], strict=False)]
    assert arrivals["r8"][-1] > expires + 5.0 and max(gaps) < 2.0, max(
        gaps
    )  # r8 puts every 0.2 s; a reconnect would take longer


def doc_commands() -> list[list[str]]:
    """The commands of docs/kubernetes.md's identity-commands block, comments dropped."""
    text = (ROOT / "docs" / "kubernetes.md").read_text("utf-8")
    block = re.search(
        r"<!-- identity-commands: begin -->\s*```bash\n(.*?)```\s*<!-- identity-commands: end -->", text, re.S
    )
    assert block is not None, "docs/kubernetes.md lost its identity-commands block"
    return [shlex.split(line) for line in block.group(1).splitlines() if line.strip() and not line.startswith("#")]


def test_adding_and_revoking_a_robot_are_one_command_each_as_the_docs_say(tmp_path: Path) -> None:
    """docs/kubernetes.md's commands, in order, from the operator's torch-free install: add writes r7's
    certificate, key and session config and a rule set naming it; revoke drops its rules and renew skips it."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command (.ci/run installs it)")
    commands = doc_commands()
    assert [c[:3] for c in commands] == [["gcdtrav", "identity", w] for w in ("add", "revoke", "renew", "list")]
    subprocess.run(["sh", str(MAKE_CERTIFICATES), "tls-out"], check=True, capture_output=True, cwd=tmp_path)
    issued = tmp_path / "tls-out" / "identities"
    outputs = []
    for command in commands:
        done = subprocess.run(torch_free_gcdtrav(*command[1:]), capture_output=True, text=True, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        outputs.append(done.stdout)
        rules = json.loads((tmp_path / "tls-out" / "access-control.json5").read_text("utf-8"))
        subjects = [s["id"] for s in rules["subjects"]]
        if command[2] == "add":
            assert {p.name for p in issued.iterdir()} == {"robot-r7.crt", "robot-r7.key", "robot-r7.json5"}
            assert "robot-r7" in subjects
            added_at = (issued / "robot-r7.crt").stat().st_mtime_ns
        else:
            assert "robot-r7" not in subjects and subjects == ["trusted", "other-routers"]
    assert (issued / "robot-r7.crt").stat().st_mtime_ns == added_at  # renew skipped the revoked robot
    assert "robot-r7" in outputs[-1] and "revoked" in outputs[-1]


def test_bad_identities_are_refused_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command (.ci/run installs it)")
    assert gcdtrav_identity("add", str(tmp_path / "nowhere"), "robot", "r7") == 1  # no CA there
    subprocess.run(["sh", str(MAKE_CERTIFICATES), str(tmp_path / "tls")], check=True, capture_output=True)
    assert gcdtrav_identity("add", str(tmp_path / "tls"), "robot", "r7/front") == 1  # not one key chunk
    assert gcdtrav_identity("add", str(tmp_path / "tls"), "robot", "**") == 1
    assert gcdtrav_identity("revoke", str(tmp_path / "tls"), "robot", "r9") == 1  # never added
    (tmp_path / "tls" / "identities.yaml").write_text("robots: [r1]\nrobtos: [r2]\n", "utf-8")  # strict
    assert gcdtrav_identity("list", str(tmp_path / "tls")) == 1
    errors = capsys.readouterr().err.splitlines()
    assert len(errors) == 5 and all(line.startswith("gcdtrav identity: ") for line in errors), errors
    assert "robtos: Extra inputs are not permitted" in errors[-1]


def test_a_robot_behind_its_acl_sees_whether_the_service_receives_its_outcomes(tmp_path: Path) -> None:
    """The relay holds its outcomes while nobody receives them (zenoh's matching status, client/relay/outcomes.py):
    behind the routers' rules the robot must still learn of the service's subscriber, and of its going."""
    with fleet(tmp_path, per_identity=True) as built:
        service, r7 = built.trusted(), built.user("robot", "r7")
        outcomes = r7.declare_publisher("gcdtrav/in/r7/front/outcomes")
        subscriber = service.declare_subscriber("gcdtrav/in/**/outcomes", lambda sample: None)
        assert wait_until(lambda: outcomes.matching_status.matching, 15)
        subscriber.undeclare()
        assert wait_until(lambda: not outcomes.matching_status.matching, 15)
