"""deploy/kubernetes renders with kustomize, and every resource is valid where it will be applied.

Built-in kinds are validated strictly (unknown fields are errors, as `kubectl apply --validate=strict`) against
the Kubernetes API schema that the kubernetes-validate package ships; KEDA's ScaledObject against KEDA's
published CRD schema (data/keda-scaledobject-v1alpha1.json, origin in its $comment), made strict the same way.
The zenoh configs load in zenoh; the settings load in gcdtrav; the parts that must agree, agree.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
TREE = ROOT / "deploy" / "kubernetes"
KUBERNETES_VERSION = "1.32.0"  # the oldest Kubernetes the manifests are meant for (sidecar-free, policy/v1)
KEDA_SCHEMA = Path(__file__).with_name("data") / "keda-scaledobject-v1alpha1.json"


def kustomize_command() -> list[str]:
    """kubectl's built-in kustomize, else the kustomize binary; CI installs kubectl (.ci/run)."""
    if shutil.which("kubectl"):
        return ["kubectl", "kustomize"]
    if shutil.which("kustomize"):
        return ["kustomize", "build"]
    if os.environ.get("CI"):
        pytest.fail("kubectl (or kustomize) is missing: .ci/run installs it")
    pytest.skip("kubectl or kustomize not installed")


def rendered(tree: Path) -> list[dict[str, Any]]:
    output = subprocess.run([*kustomize_command(), str(tree)], capture_output=True, text=True, timeout=60)
    assert output.returncode == 0, output.stderr
    return [doc for doc in yaml.safe_load_all(output.stdout) if doc]


@pytest.fixture(scope="module")
def keda_tree() -> list[dict[str, Any]]:
    return rendered(TREE)


@pytest.fixture(scope="module")
def hpa_tree() -> list[dict[str, Any]]:
    return rendered(TREE / "hpa")


def one(resources: list[dict[str, Any]], kind: str, name: str | None = None) -> dict[str, Any]:
    found = [r for r in resources if r["kind"] == kind and (name is None or r["metadata"]["name"] == name)]
    assert len(found) == 1, (kind, name, [r["metadata"]["name"] for r in found])
    return found[0]


def strict(schema: Any) -> Any:
    """An OpenAPI v3 schema with unknown properties forbidden wherever the CRD lists the properties (what
    the API server's strict field validation rejects); maps and preserved fields stay open."""
    if isinstance(schema, list):
        return [strict(item) for item in schema]
    if not isinstance(schema, dict):
        return schema
    closed = {key: strict(value) for key, value in schema.items()}
    open_ = "additionalProperties" in closed or closed.get("x-kubernetes-preserve-unknown-fields")
    if "properties" in closed and not open_:
        closed["additionalProperties"] = False
    return closed


def validate_keda(resource: dict[str, Any]) -> None:
    import jsonschema

    schema = strict(json.loads(KEDA_SCHEMA.read_text("utf-8"))["openAPIV3Schema"])
    jsonschema.validate(resource, schema, cls=jsonschema.Draft4Validator)


def validate_builtin(resource: dict[str, Any]) -> None:
    import kubernetes_validate

    kubernetes_validate.validate(resource, KUBERNETES_VERSION, strict=True)


@pytest.mark.parametrize("tree", ["keda", "hpa"])
def test_every_resource_validates(tree: str, request: pytest.FixtureRequest) -> None:
    resources = request.getfixturevalue(f"{tree}_tree")
    for resource in resources:
        if resource["apiVersion"].startswith("keda.sh/"):
            validate_keda(resource)
        else:
            validate_builtin(resource)
    kinds = sorted({r["kind"] for r in resources})
    autoscaler = "ScaledObject" if tree == "keda" else "HorizontalPodAutoscaler"
    for kind in ("ConfigMap", "Deployment", "PodDisruptionBudget", "Secret", "Service", "StatefulSet", autoscaler):
        assert kind in kinds, kinds
    assert not ({"ScaledObject", "HorizontalPodAutoscaler"} - {autoscaler}) & set(kinds), "one autoscaler only"
    assert {r["metadata"].get("namespace") for r in resources if r["kind"] != "Namespace"} == {"gcdtrav"}


def test_the_validation_rejects_what_the_cluster_would(keda_tree: list[dict[str, Any]]) -> None:
    """The checks can fail: an unknown field, a wrong type, in a built-in kind and in the ScaledObject."""
    import copy

    import jsonschema
    import kubernetes_validate

    deployment = copy.deepcopy(one(keda_tree, "Deployment"))
    deployment["spec"]["template"]["spec"]["containers"][0]["readinessProbes"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        validate_builtin(deployment)
    scaled = copy.deepcopy(one(keda_tree, "ScaledObject"))
    scaled["spec"]["maxReplicas"] = 20  # the HPA's name, not KEDA's
    with pytest.raises(jsonschema.ValidationError):
        validate_keda(scaled)
    scaled = copy.deepcopy(one(keda_tree, "ScaledObject"))
    scaled["spec"]["minReplicaCount"] = "2"
    with pytest.raises(jsonschema.ValidationError):
        validate_keda(scaled)


def container(resources: list[dict[str, Any]], kind: str, name: str) -> dict[str, Any]:
    return one(resources, kind, name)["spec"]["template"]["spec"]["containers"][0]  # type: ignore[no-any-return]


def secret_file(resources: list[dict[str, Any]], prefix: str, key: str) -> str:
    found = [r for r in resources if r["kind"] == "Secret" and r["metadata"]["name"].startswith(prefix)]
    assert len(found) == 1
    return base64.b64decode(found[0]["data"][key]).decode()


def test_the_zenoh_configs_load_and_the_routers_connect_by_pod_dns(keda_tree: list[dict[str, Any]]) -> None:
    import zenoh

    router_conf = zenoh.Config.from_json5(secret_file(keda_tree, "gcdtrav-router-zenoh", "router.json5"))
    service_conf = zenoh.Config.from_json5(secret_file(keda_tree, "gcdtrav-service-zenoh", "zenoh.json5"))
    for conf in (router_conf, service_conf):
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    # The access control of deploy/access-control.json5, where the robots' sessions arrive.
    reference = zenoh.Config.from_json5((ROOT / "deploy" / "access-control.json5").read_text("utf-8"))
    assert json.loads(router_conf.get_json("access_control")) == json.loads(reference.get_json("access_control"))
    routers = one(keda_tree, "StatefulSet", "gcdtrav-router")
    assert routers["spec"]["replicas"] >= 2 and routers["spec"]["serviceName"] == "gcdtrav-router"
    headless = one(keda_tree, "Service", "gcdtrav-router")
    assert headless["spec"]["clusterIP"] == "None" and headless["spec"]["publishNotReadyAddresses"] is True
    pods = [f"gcdtrav-router-{i}" for i in range(routers["spec"]["replicas"])]
    env = {e["name"]: e.get("value") for e in container(keda_tree, "StatefulSet", "gcdtrav-router")["env"]}
    assert env["ROUTERS"].split() == pods  # each connects to the others, never itself (the start script)
    endpoints = json.loads(service_conf.get_json("connect/endpoints"))
    assert endpoints == [f"tls/{pod}.gcdtrav-router:7447" for pod in pods]
    users = {line.split(":")[0] for line in secret_file(keda_tree, "gcdtrav-router-zenoh", "credentials.txt").split()}
    assert json.loads(service_conf.get_json("transport/auth/usrpwd/user")) in users
    assert json.loads(router_conf.get_json("transport/auth/usrpwd/user")) in users


def test_the_service_pods_settings_probes_and_grace(keda_tree: list[dict[str, Any]], tmp_path: Path) -> None:
    from gcdtrav.schemas.settings import load_settings
    from gcdtrav.schemas.settings.env import unknown_setting

    deployment = one(keda_tree, "Deployment", "gcdtrav")
    pod = deployment["spec"]["template"]["spec"]
    main = pod["containers"][0]
    settings_map = next(r for r in keda_tree if r["kind"] == "ConfigMap")
    (tmp_path / "service.yaml").write_text(settings_map["data"]["service.yaml"], "utf-8")
    (tmp_path / "anchors.yaml").write_text(settings_map["data"]["anchors.yaml"], "utf-8")
    env = {e["name"]: e for e in main["env"]}
    assert env["GCDTRAV_INSTANCE"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    literal = {name: e["value"] for name, e in env.items() if name.startswith("GCDTRAV_") and "value" in e}
    for name in [*literal, "GCDTRAV_INSTANCE"]:
        assert unknown_setting(name.removeprefix("GCDTRAV_").lower().split("__")) is None, name
    environ = {**literal, "GCDTRAV_INSTANCE": "gcdtrav-5d9c7b7f6d-x2x7q"}  # a pod's name is a valid instance
    settings = load_settings(tmp_path / "service.yaml", environ=environ)
    from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set

    assert str(settings.anchors_file) == "/etc/gcdtrav/anchors.yaml"
    assert AnchorSet.load(tmp_path / "anchors.yaml").version == default_anchor_set().version
    ports = {p["name"]: p["containerPort"] for p in main["ports"]}
    assert ports["health"] == settings.health_port and settings.health_address == "0.0.0.0"
    assert ports["metrics"] == int(literal["GCDTRAV_METRICS_PORT"])
    metrics = one(keda_tree, "Service", "gcdtrav-metrics")
    assert metrics["spec"]["ports"][0]["targetPort"] == "metrics"
    assert metrics["spec"]["selector"] == deployment["spec"]["selector"]["matchLabels"]
    assert main["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "health"}
    assert main["livenessProbe"]["httpGet"] == {"path": "/livez", "port": "health"}
    assert pod["terminationGracePeriodSeconds"] > settings.shutdown_grace_s + 5  # the process exits first
    assert deployment["spec"]["strategy"]["rollingUpdate"] == {"maxSurge": 1, "maxUnavailable": 0}
    assert one(keda_tree, "PodDisruptionBudget", "gcdtrav")["spec"]["maxUnavailable"] == 1
    assert pod["affinity"]["podAntiAffinity"]
    assert main["resources"]["limits"]["cpu"] == main["resources"]["requests"]["cpu"]  # whole torch threads
    mounts = {m["mountPath"] for m in main["volumeMounts"]}
    model = Path(literal["GCDTRAV_MODEL"])
    assert str(model.parent) in mounts and str(settings.anchors_file) in mounts
    weights = pod["initContainers"][0]
    assert weights["command"][-1] == f"{model.parent}/" and weights["command"][-2].endswith(f"/{model.name}")


def test_keda_and_the_hpa_scale_on_the_same_signal(
    keda_tree: list[dict[str, Any]], hpa_tree: list[dict[str, Any]]
) -> None:
    """desired = ceil(inference seconds per second / 0.7) either way: an average per pod, the same bounds."""
    scaled = one(keda_tree, "ScaledObject", "gcdtrav")["spec"]
    hpa = one(hpa_tree, "HorizontalPodAutoscaler", "gcdtrav")["spec"]
    trigger = scaled["triggers"][0]
    assert trigger["type"] == "prometheus" and trigger["metricType"] == "AverageValue"
    external = hpa["metrics"][0]["external"]
    assert external["target"] == {"type": "AverageValue", "averageValue": "700m"}
    assert float(trigger["metadata"]["threshold"]) == 0.7
    assert (scaled["minReplicaCount"], scaled["maxReplicaCount"]) == (hpa["minReplicas"], hpa["maxReplicas"])
    assert scaled["advanced"]["horizontalPodAutoscalerConfig"]["behavior"] == hpa["behavior"]
    assert scaled["scaleTargetRef"]["name"] == hpa["scaleTargetRef"]["name"] == "gcdtrav"
    adapter = yaml.safe_load((TREE / "hpa" / "prometheus-adapter-rules.yaml").read_text("utf-8"))
    rule = adapter["rules"]["external"][0]
    assert rule["name"]["as"] == external["metric"]["name"]
    assert "gcdtrav_inference_seconds_sum" in rule["seriesQuery"]
    for query in (trigger["metadata"]["query"], rule["metricsQuery"]):
        assert query.startswith("sum(rate(") and "[2m]))" in query
    assert "gcdtrav_inference_seconds_sum" in trigger["metadata"]["query"]
