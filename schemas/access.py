"""Who may do what on the fleet's routers: identities in, zenoh's access control out (docs/kubernetes.md,
"Security").

Each robot, planner and operator outside the cluster proves who it is by its own client certificate (mTLS on
the routers' identity endpoint); the certificate's common name is ``{role}-{name}`` (``robot-r7``). The rules
are generated from the identity list, one subject per identity, because zenoh's access control has no key
templates: a rule cannot say "the robot's own keys" for every robot at once. Subjects match by
``cert_common_names``; a session matching several subjects gets what any of them allows (zenoh's
interceptor), so no password role grants anything here: the shared logins only admit a session to the
handshake (zenoh requires one from every session once the routers hold a dictionary).

What each role may do, per key (P = the service's prefix, R = the robot's name, D = a ROS domain):

- a robot R: put under P/in/R/**, P/relay/R/** and its ROS topics D/R/** (rmw_zenoh's keys of namespace /R);
  subscribe to and query its own outputs P/out/R/**, its credits P/credit/R/**; watch the service's
  liveliness; ROS graph tokens of namespace /R only; queryables only on its ROS keys. The routers send it
  nothing else (egress rules), so a subscription to ``**`` gets only its own keys.
- a planner: put planned paths for any robot; subscribe to and query every output, the credits and relays'
  health (why a robot's maps are stale), the service's status.
- an operator: query and swap the anchor set (P/config/**), answer questions, read every key under P.
"""

from __future__ import annotations

from typing import Any

from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.strict import StrictModel
from pydantic import Field

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$"  # one key chunk without wildcards, and a certificate name
ROLES = ("robot", "planner", "operator")
ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]
WATCH = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
DATA = ["put", "delete", "query", "reply"]
# Declarations the routers pass to everyone: a client sends a put only where it knows a subscriber whose
# expression meets it (zenoh's writer-side filtering), and the service subscribes to P/in/**, which no
# robot's own expression includes (the ACL tests inclusion). A robot so learns which expressions others
# subscribe to, never their data: data (put, reply) is sent to it on its own keys only.
DECLARATIONS = ["declare_subscriber", "declare_queryable"]
# A robot's ROS rights are its namespace's keys, D/<name>/**: a robot named like a topic every robot shares
# (/tf, /odom, ...) would get put rights on that topic for the whole fleet (rmw_zenoh's key of /tf is D/tf/...).
SHARED_TOPICS = frozenset(
    {
        "tf", "tf_static", "rosout", "parameter_events", "clock", "diagnostics", "robot_description",
        "joint_states", "map", "map_metadata", "odom", "cmd_vel", "scan", "plan", "goal_pose", "initialpose",
    }
)  # fmt: skip
ROUTER_COMMON_NAME = "gcdtrav-router"  # the routers' certificate (deploy/kubernetes/tls/make-certificates.sh)
# "**" does not include keys whose first chunk starts with "@" (rmw_zenoh's graph tokens): named on their own.
EVERY_KEY = ["**", "@ros2_lv/**"]
TRUSTED_USERS = ["gcdtrav-service", "router"]  # inside the cluster, by password on the internal endpoint


class FleetIdentities(StrictModel):
    """The identity list (``identities.yaml``): who holds a certificate of the fleet's CA, by role."""

    prefix: str = Field(default="gcdtrav", description="The service's key prefix (settings zenoh.prefix).")
    endpoint: str = Field(
        default="tls/gcdtrav-router-public:7448",
        description="The routers' identity endpoint, as the identities' session configs name it.",
    )
    ros_domains: list[int] = Field(
        default=[0], description="ROS_DOMAIN_IDs whose rmw_zenoh keys robots may use (D/<robot>/**)."
    )
    robots: list[str] = Field(default_factory=list, description="Robot names: its sources are <name> and <name>/*.")
    planners: list[str] = Field(default_factory=list)
    operators: list[str] = Field(default_factory=list)
    revoked: list[str] = Field(
        default_factory=list, description="Common names refused: no rule, no renewal (identity revoke)."
    )

    def model_post_init(self, _context: Any) -> None:
        import re

        for role in ROLES:
            for name in self.names(role):
                if not re.match(NAME_PATTERN, name):
                    raise ValueError(f"{role} name '{name}': letters, digits, '_', '.', '-' only (a key chunk)")
        shared = sorted(SHARED_TOPICS.intersection(self.robots))
        if shared:
            raise ValueError(
                f"robot name '{shared[0]}' is a ROS topic robots share: its rights on D/{shared[0]}/** would cover "
                f"every robot's /{shared[0]}"
            )
        common = [common_name(role, n) for role in ROLES for n in self.names(role)]
        if len(common) != len(set(common)):
            raise ValueError("an identity is listed twice")

    def names(self, role: str) -> list[str]:
        return {"robot": self.robots, "planner": self.planners, "operator": self.operators}[role]

    def active(self, role: str) -> list[str]:
        """The names of ``role`` not revoked."""
        return [n for n in self.names(role) if common_name(role, n) not in self.revoked]


def common_name(role: str, name: str) -> str:
    """The certificate's common name of an identity, the ACL's subject: ``robot-r7``."""
    return f"{role}-{name}"


def _rule(rule_id: str, flows: list[str], messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": flows, "messages": messages, "key_exprs": key_exprs}


def robot_rules(name: str, identities: FleetIdentities) -> list[dict[str, Any]]:
    """What robot ``name`` may send (ingress) and be sent (egress): its own keys, the service's liveliness."""
    keys, rid = Keys(identities.prefix), f"robot-{name}"
    ros = [f"{d}/{name}/**" for d in identities.ros_domains]
    ros_tokens = [f"@ros2_lv/{d}/*/*/*/*/*/%{name}/**" for d in identities.ros_domains]  # namespace /name
    graph = [f"@ros2_lv/{d}/**" for d in identities.ros_domains]
    inputs = [f"{keys.prefix}/in/{name}/**", f"{keys.prefix}/relay/{name}/**"]
    outputs = [f"{keys.prefix}/out/{name}/**", keys.credit(f"{name}/**")]
    liveliness = [keys.alive("**"), keys.member("**"), keys.active_anchors("**")]
    return [
        _rule(f"{rid}-puts", ["ingress"], ["put", "delete"], inputs + ros),
        _rule(f"{rid}-reads", ["ingress"], ["declare_subscriber", "query"], outputs + inputs + ros),
        _rule(f"{rid}-ros", ["ingress"], ["declare_queryable", "reply", "liveliness_token"], ros + ros_tokens),
        # rmw_zenoh's graph: it may watch the whole ROS graph's tokens; it is sent only its own (egress below)
        _rule(f"{rid}-watch", ["ingress"], ["declare_liveliness_subscriber", "liveliness_query"], liveliness + graph),
        _rule(f"{rid}-sent", ["egress"], DATA, outputs + inputs + ros),
        _rule(f"{rid}-tokens", ["egress"], ["liveliness_token", "liveliness_query"], liveliness + ros_tokens),
        _rule(f"{rid}-declarations", ["egress"], DECLARATIONS, ["**"]),
    ]


def planner_rules(name: str, identities: FleetIdentities) -> list[dict[str, Any]]:
    keys, pid = Keys(identities.prefix), f"planner-{name}"
    # every robot's outputs, and what says why they are stale (credits, relays' health), the service's status
    reads = [keys.outputs, keys.credit("**"), keys.relay_health("**"), keys.status]
    return [
        _rule(f"{pid}-paths", ["ingress"], ["put", "delete"], [keys.planned_path("**")]),
        _rule(f"{pid}-reads", ["ingress"], WATCH, [*reads, keys.alive("**"), keys.member("**")]),
        _rule(f"{pid}-sent", ["egress"], DATA, [*reads, keys.planned_path("**")]),
        _rule(
            f"{pid}-tokens", ["egress"], ["liveliness_token", "liveliness_query"], [keys.alive("**"), keys.member("**")]
        ),
        _rule(f"{pid}-declarations", ["egress"], DECLARATIONS, ["**"]),
    ]


def operator_rules(name: str, identities: FleetIdentities) -> list[dict[str, Any]]:
    keys, oid = Keys(identities.prefix), f"operator-{name}"
    return [
        _rule(f"{oid}-answers", ["ingress"], ["put", "query"], [keys.answer("**")]),
        _rule(f"{oid}-reads", ["ingress"], WATCH, [f"{keys.prefix}/**"]),
        _rule(f"{oid}-sent", ["egress"], ALL_MESSAGES, [f"{keys.prefix}/**"]),
        _rule(f"{oid}-declarations", ["egress"], DECLARATIONS, ["**"]),
    ]


RULES = {"robot": robot_rules, "planner": planner_rules, "operator": operator_rules}


def access_control(identities: FleetIdentities) -> dict[str, Any]:
    """zenoh's ``access_control`` section: the trusted (service pods, routers) get everything; each identity
    its own rules; anything else (a revoked certificate, a password alone) nothing."""
    rules = [_rule("trusted", ["ingress", "egress"], ALL_MESSAGES, EVERY_KEY)]
    subjects: list[dict[str, Any]] = [
        {"id": "trusted", "usernames": TRUSTED_USERS},
        {"id": "other-routers", "cert_common_names": [ROUTER_COMMON_NAME]},
    ]
    policies: list[dict[str, Any]] = [{"rules": ["trusted"], "subjects": ["trusted", "other-routers"]}]
    for role in ROLES:
        for name in identities.active(role):
            own = RULES[role](name, identities)
            subject = common_name(role, name)
            rules += own
            subjects.append({"id": subject, "cert_common_names": [subject]})
            policies.append({"rules": [r["id"] for r in own], "subjects": [subject]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
