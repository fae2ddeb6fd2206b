"""`gcdtrav identity add|revoke|renew|list DIR`: each robot, planner and operator its own certificate, and the
routers' access control generated from the list (gcdtrav.schemas.access; docs/kubernetes.md "Security").

DIR is the fleet's TLS folder of deploy/kubernetes/tls/make-certificates.sh (its ca.crt and ca.key sign the
identities; keep it offline). It holds:

  identities.yaml            the list (gcdtrav.schemas.access.FleetIdentities), edited by these commands
  access-control.json5       zenoh's access_control for the routers, rewritten by every command
  identities/ROLE-NAME.crt   the identity's certificate (CN ROLE-NAME), ROLE-NAME.key its key, and
  identities/ROLE-NAME.json5 its zenoh session config (the routers' identity endpoint, mTLS, the shared login)

Certificates are short-lived (--valid-hours, default 24) and renewed by `renew` (run it as a job, more often
than the lifetime); the routers close a link when its certificate expires. Revoking is therefore: no renewal,
no rule. The identity is refused on the routers' next rollout with the new access control, and in any case
once its last certificate expires (at most --valid-hours).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml
from gcdtrav.schemas.access import ROLES, FleetIdentities, access_control, common_name
from gcdtrav.schemas.strict import problems
from pydantic import ValidationError

COMMANDS = ("identity",)
LOGINS = {"robot": "robot", "planner": "planner", "operator": "operator"}  # credentials.txt: admission only
CLOCK_SKEW = dt.timedelta(minutes=5)  # a certificate is valid from a little before now: routers' clocks differ


class IdentityError(ValueError):
    """A refused identity command: one line for the operator."""


def add_identity_command(commands: argparse._SubParsersAction) -> None:
    identity = commands.add_parser("identity", help="per-identity certificates and the routers' access control")
    actions = identity.add_subparsers(dest="action", required=True)
    for action, what in (("add", "issue a certificate"), ("revoke", "refuse an identity")):
        parser = actions.add_parser(action, help=f"{what} and rewrite access-control.json5")
        parser.add_argument("dir", help="the fleet's TLS folder (ca.crt, ca.key: make-certificates.sh)")
        parser.add_argument("role", choices=ROLES)
        parser.add_argument("name", help="e.g. r7: the robot's sources are r7 and r7/<camera>")
        add_validity(parser)
    renew = actions.add_parser("renew", help="reissue every certificate not revoked (run as a job)")
    renew.add_argument("dir")
    add_validity(renew)
    listing = actions.add_parser("list", help="identities, their certificates' expiry, the revoked")
    listing.add_argument("dir")


def add_validity(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--valid-hours", type=float, default=24.0, help="certificate lifetime [default: 24]")
    parser.add_argument(
        "--endpoint", help="the routers' identity endpoint, kept in identities.yaml [tls/gcdtrav-router-public:7448]"
    )


def run(args: argparse.Namespace) -> int:
    try:
        print("\n".join(act(args)))
    except IdentityError as err:
        print(f"gcdtrav identity: {err}", file=sys.stderr)
        return 1
    return 0


def act(args: argparse.Namespace) -> list[str]:
    folder = Path(args.dir)
    identities = load(folder)
    if args.action == "list":
        return listing(folder, identities)
    valid = dt.timedelta(hours=args.valid_hours)
    if args.endpoint:
        identities = identities.model_copy(update={"endpoint": args.endpoint})
    if args.action == "add":
        identities = added(identities, args.role, args.name)
        issue(folder, args.role, args.name, valid, identities.endpoint)
        done = [f"issued {folder / 'identities' / common_name(args.role, args.name)}.crt, valid {valid}"]
    elif args.action == "revoke":
        identities = revoked(identities, args.role, args.name)
        done = [f"revoked {common_name(args.role, args.name)}: refused on the routers' rollout, else at expiry"]
    else:
        done = [renewed(folder, role, name, valid, identities.endpoint) for role, name in active(identities)]
    save(folder, identities)
    return [*done, f"wrote {folder / 'access-control.json5'}: apply it to the routers (docs/kubernetes.md)"]


def load(folder: Path) -> FleetIdentities:
    if not (folder / "ca.key").is_file():
        raise IdentityError(f"{folder}: no ca.key (make it with deploy/kubernetes/tls/make-certificates.sh)")
    path = folder / "identities.yaml"
    try:
        return FleetIdentities.model_validate(yaml.safe_load(path.read_text("utf-8")) or {} if path.exists() else {})
    except (ValueError, yaml.YAMLError) as err:
        raise IdentityError(f"{path}: {one_line(err)}") from None


def one_line(err: Exception) -> str:
    """A validation error as the operator reads it: each field and what is wrong, on one line."""
    return problems(err) if isinstance(err, ValidationError) else str(err).replace("\n", " ")


def save(folder: Path, identities: FleetIdentities) -> None:
    text = yaml.safe_dump(identities.model_dump(), sort_keys=False)
    (folder / "identities.yaml").write_text(text, "utf-8")
    rules = json.dumps(access_control(identities), indent=1)
    (folder / "access-control.json5").write_text(rules + "\n", "utf-8")


def active(identities: FleetIdentities) -> list[tuple[str, str]]:
    return [(role, name) for role in ROLES for name in identities.active(role)]


def added(identities: FleetIdentities, role: str, name: str) -> FleetIdentities:
    listed = identities.names(role)
    fields = {f"{role}s": listed if name in listed else [*listed, name]}
    revoked_names = [n for n in identities.revoked if n != common_name(role, name)]  # adding again re-admits
    try:
        return FleetIdentities.model_validate({**identities.model_dump(), **fields, "revoked": revoked_names})
    except ValueError as err:
        raise IdentityError(one_line(err)) from None


def revoked(identities: FleetIdentities, role: str, name: str) -> FleetIdentities:
    if name not in identities.names(role):
        raise IdentityError(f"no {role} '{name}' in identities.yaml")
    revoked_names = sorted({*identities.revoked, common_name(role, name)})
    return identities.model_copy(update={"revoked": revoked_names})


def renewed(folder: Path, role: str, name: str, valid: dt.timedelta, endpoint: str) -> str:
    issue(folder, role, name, valid, endpoint)
    return f"renewed {common_name(role, name)}"


def issue(folder: Path, role: str, name: str, valid: dt.timedelta, endpoint: str) -> None:
    """A key and a certificate CN=ROLE-NAME (client auth) signed by the fleet's CA, and the session config."""
    out, subject = folder / "identities", common_name(role, name)
    out.mkdir(exist_ok=True)
    now = dt.datetime.now(dt.timezone.utc)
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        (work / "index.txt").write_text("", "utf-8")
        (work / "ca.cnf").write_text(CA_CONFIG.format(ca=folder.resolve(), work=work), "utf-8")
        key, request, certificate = work / "key.pem", work / "request.csr", work / "certificate.pem"
        openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={subject}", "-keyout", key, "-out", request)
        key.chmod(0o600)
        openssl(
            "ca", "-batch", "-notext", "-config", work / "ca.cnf", "-in", request, "-out", certificate,
            "-startdate", stamp(now - CLOCK_SKEW), "-enddate", stamp(now + valid),
        )  # fmt: skip
        # the pair moves in only once signed: a failed signing leaves the identity's old key and certificate
        shutil.move(key, out / f"{subject}.key")
        shutil.move(certificate, out / f"{subject}.crt")
    (out / f"{subject}.json5").write_text(session_config(folder, subject, role, endpoint), "utf-8")


def stamp(moment: dt.datetime) -> str:
    return moment.strftime("%Y%m%d%H%M%SZ")


def openssl(*arguments: object) -> None:
    try:
        done = subprocess.run(["openssl", *map(str, arguments)], capture_output=True, text=True, timeout=60)
    except FileNotFoundError:
        raise IdentityError("the openssl command is not installed") from None
    if done.returncode != 0:
        raise IdentityError(f"openssl {arguments[0]}: {done.stderr.strip().splitlines()[-1:]}")


def session_config(folder: Path, subject: str, role: str, endpoint: str) -> str:
    """The identity's zenoh client config: its certificate on the identity endpoint, the role's shared login."""
    config = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": "ca.crt",
                    "connect_certificate": f"{subject}.crt",
                    "connect_private_key": f"{subject}.key",
                    "enable_mtls": True,  # zenoh sends the certificate only with this set on the client too
                    "verify_name_on_connect": True,
                }
            },
            "auth": {"usrpwd": {"user": LOGINS[role], "password": "change-me"}},
        },
    }
    note = f"// {subject}'s zenoh session (gcdtrav identity); paths relative to where it runs: copy ca.crt too.\n"
    return note + json.dumps(config, indent=1) + "\n"


def listing(folder: Path, identities: FleetIdentities) -> list[str]:
    lines = []
    for role in ROLES:
        for name in identities.names(role):
            subject = common_name(role, name)
            state = "revoked" if subject in identities.revoked else expiry(folder / "identities" / f"{subject}.crt")
            lines.append(f"{subject:<28} {state}")
    return lines or ["no identities"]


def expiry(certificate: Path) -> str:
    if not certificate.exists():
        return "no certificate"
    done = subprocess.run(
        ["openssl", "x509", "-noout", "-enddate", "-in", str(certificate)], capture_output=True, text=True
    )
    return "valid until " + done.stdout.strip().removeprefix("notAfter=")


CA_CONFIG = """[ ca ]
default_ca = fleet
[ fleet ]
database = {work}/index.txt
new_certs_dir = {work}
certificate = {ca}/ca.crt
private_key = {ca}/ca.key
rand_serial = yes
default_md = sha256
policy = any
unique_subject = no
copy_extensions = none
x509_extensions = client
[ any ]
commonName = supplied
[ client ]
basicConstraints = critical,CA:FALSE
keyUsage = critical,digitalSignature,keyEncipherment
extendedKeyUsage = clientAuth
"""
