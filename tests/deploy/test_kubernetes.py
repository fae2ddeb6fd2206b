"""deploy/kubernetes renders with kustomize, and every resource is valid where it will be applied.

Built-in kinds are validated strictly (unknown fields are errors, as `kubectl apply --validate=strict`) against
the Kubernetes API schema that the kubernetes-validate package ships; custom resources against their projects'
published CRD schemas (data/*.json, origin and licence in each $comment), made strict the same way: KEDA's
ScaledObject, the Prometheus Operator's ServiceMonitor and PodMonitor, CloudNativePG's Cluster. The optional
components (monitoring/, postgresql/) are rendered in an overlay as an operator would include them.
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
DATA = Path(__file__).with_name("data")
KEDA_SCHEMA = DATA / "keda-scaledobject-v1alpha1.json"
CRD_SCHEMAS = {  # (apiVersion, kind): the CRD's published schema
    ("keda.sh/v1alpha1", "ScaledObject"): KEDA_SCHEMA,
    ("monitoring.coreos.com/v1", "ServiceMonitor"): DATA / "monitoring-servicemonitor-v1.json",
    ("monitoring.coreos.com/v1", "PodMonitor"): DATA / "monitoring-podmonitor-v1.json",
    ("postgresql.cnpg.io/v1", "Cluster"): DATA / "cnpg-cluster-v1.json",
}
FIRST_START = ROOT / "benchmarks" / "first-start-ort-int8-2026-11-27.json"  # benchmarks/first_start.py


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


def validate_custom(resource: dict[str, Any]) -> None:
    """Against its CRD's schema; a kind without one here fails."""
    import jsonschema

    path = CRD_SCHEMAS[(resource["apiVersion"], resource["kind"])]
    schema = strict(json.loads(path.read_text("utf-8"))["openAPIV3Schema"])
    jsonschema.validate(resource, schema, cls=jsonschema.Draft4Validator)


def validate_builtin(resource: dict[str, Any]) -> None:
    import kubernetes_validate

    kubernetes_validate.validate(resource, KUBERNETES_VERSION, strict=True)


def validate(resource: dict[str, Any]) -> None:
    """A custom resource against its CRD's schema, a built-in kind against Kubernetes' (an unknown kind fails)."""
    if (resource["apiVersion"], resource["kind"]) in CRD_SCHEMAS:
        validate_custom(resource)
    else:
        validate_builtin(resource)


@pytest.mark.parametrize("tree", ["keda", "hpa"])
def test_every_resource_validates(tree: str, request: pytest.FixtureRequest) -> None:
    resources = request.getfixturevalue(f"{tree}_tree")
    for resource in resources:
        validate(resource)
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
        validate_custom(scaled)
    scaled = copy.deepcopy(one(keda_tree, "ScaledObject"))
    scaled["spec"]["minReplicaCount"] = "2"
    with pytest.raises(jsonschema.ValidationError):
        validate_custom(scaled)


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
    # One HTTP port for the probes and the metrics (service/runtime/http_endpoints.py), set in the settings.
    assert [p["name"] for p in main["ports"]] == ["http"]
    assert main["ports"][0]["containerPort"] == settings.health_port == settings.metrics_port
    assert settings.health_address == settings.metrics_address == "0.0.0.0"
    metrics = one(keda_tree, "Service", "gcdtrav-metrics")
    assert metrics["spec"]["ports"][0]["targetPort"] == "http"
    assert metrics["metadata"]["annotations"]["prometheus.io/port"] == str(settings.metrics_port)
    assert metrics["spec"]["selector"] == deployment["spec"]["selector"]["matchLabels"]
    assert main["startupProbe"]["httpGet"] == {"path": "/livez", "port": "http"}
    assert main["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "http"}
    assert main["livenessProbe"]["httpGet"] == {"path": "/livez", "port": "http"}
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


@pytest.mark.parametrize("tree", ["keda", "hpa"])
def test_no_replicas_where_an_autoscaler_owns_the_count(tree: str, request: pytest.FixtureRequest) -> None:
    """A replicas field would reset the fleet to it at every `kubectl apply -k` (issue 47: 2 pods at once)."""
    deployment = one(request.getfixturevalue(f"{tree}_tree"), "Deployment", "gcdtrav")
    assert "replicas" not in deployment["spec"]


def test_probes_do_not_flap_on_one_slow_answer(keda_tree: list[dict[str, Any]]) -> None:
    """A busy pod's one slow probe takes it out of no Service and restarts nothing; a stalled one goes."""
    from gcdtrav.schemas.settings import ServiceSettings

    main = container(keda_tree, "Deployment", "gcdtrav")
    for name in ("readinessProbe", "livenessProbe", "startupProbe"):
        probe = main[name]
        assert probe["failureThreshold"] >= 3 and probe["timeoutSeconds"] >= 2, name
    ready = main["readinessProbe"]
    assert ready.get("successThreshold", 1) == 1  # back in at once
    live = main["livenessProbe"]
    stall_after_s = ServiceSettings().stall_after_s
    assert live["periodSeconds"] * live["failureThreshold"] > 10 * stall_after_s  # long after it left the fleet
    startup = main["startupProbe"]
    measured = json.loads(FIRST_START.read_text("utf-8"))["ready_after_s"]
    assert startup["periodSeconds"] * startup["failureThreshold"] >= 3 * measured  # a slower node still starts


def mebibytes(quantity: str) -> float:
    units = {"Ki": 2**-10, "Mi": 1, "Gi": 2**10}
    return float(quantity[:-2]) * units[quantity[-2:]] if quantity[-2:] in units else float(quantity) / 2**20


def test_a_first_start_fits_its_limits_as_measured(keda_tree: list[dict[str, Any]], tmp_path: Path) -> None:
    """The ConfigMap's precision is a fixed mode (no per-pod measurement: every pod the same mode); TMPDIR is on
    the data volume; memory and the volume hold the peaks benchmarks/first_start.py measured with these settings."""
    from gcdtrav.schemas.settings import load_settings

    settings_map = next(r for r in keda_tree if r["kind"] == "ConfigMap")
    (tmp_path / "service.yaml").write_text(settings_map["data"]["service.yaml"], "utf-8")
    settings = load_settings(tmp_path / "service.yaml", environ={})
    assert settings.precision != "auto"
    measured = json.loads(FIRST_START.read_text("utf-8"))
    assert measured["settings"] == "deploy/kubernetes/base/config/service.yaml"
    pod = one(keda_tree, "Deployment", "gcdtrav")["spec"]["template"]["spec"]
    main = pod["containers"][0]
    tmpdir = next(e["value"] for e in main["env"] if e["name"] == "TMPDIR")
    mounts = {m["mountPath"]: m["name"] for m in main["volumeMounts"]}
    volumes = {v["name"]: v for v in pod["volumes"]}
    assert mounts[tmpdir] == mounts["/var/lib/gcdtrav"] == "data"  # TMPDIR, state and cache: one volume
    assert "emptyDir" in volumes["data"]
    written = measured["peak_tmpdir_mib"] + measured["peak_cache_mib"]
    assert mebibytes(volumes["data"]["emptyDir"]["sizeLimit"]) >= 1.5 * written
    assert mebibytes(main["resources"]["requests"]["memory"]) >= 1.1 * measured["peak_rss_mib"]
    assert mebibytes(main["resources"]["limits"]["memory"]) >= mebibytes(main["resources"]["requests"]["memory"])


def overlay(tmp_path: Path, base: Path, components: list[str], **fields: Any) -> list[dict[str, Any]]:
    """Render an operator's overlay: ``base`` and ``components`` (paths under deploy/kubernetes) included."""
    kustomization = {
        "apiVersion": "kustomize.config.k8s.io/v1beta1",
        "kind": "Kustomization",
        "namespace": "gcdtrav",
        "resources": [os.path.relpath(base, tmp_path)],
        "components": [os.path.relpath(TREE / c, tmp_path) for c in components],
        **fields,
    }
    (tmp_path / "kustomization.yaml").write_text(yaml.safe_dump(kustomization), "utf-8")
    return rendered(tmp_path)


def test_the_autoscaler_query_filters_on_the_namespace_kustomize_sets(
    keda_tree: list[dict[str, Any]], tmp_path: Path
) -> None:
    """Not hard-coded: the ScaledObject's query names the namespace the fleet is rendered into."""
    query = one(keda_tree, "ScaledObject", "gcdtrav")["spec"]["triggers"][0]["metadata"]["query"]
    assert 'namespace="gcdtrav"' in query
    shutil.copy(TREE / "fleet-namespace.yaml", tmp_path)  # as docs/kubernetes.md tells an overlay to
    moved = overlay(tmp_path, TREE, [], namespace="robots-eu", replacements=[{"path": "fleet-namespace.yaml"}])
    query = one(moved, "ScaledObject", "gcdtrav")["spec"]["triggers"][0]["metadata"]["query"]
    assert 'namespace="robots-eu"' in query and 'gcdtrav"' not in query


@pytest.mark.parametrize(
    ("component", "kind"), [("monitoring", "ServiceMonitor"), ("monitoring/podmonitor", "PodMonitor")]
)
def test_the_prometheus_operator_scrapes_the_pods_http_port(component: str, kind: str, tmp_path: Path) -> None:
    """The ServiceMonitor and the PodMonitor validate against the operator's CRD schema and name the port that
    serves /metrics; a misspelt field is refused."""
    import copy

    import jsonschema

    resources = overlay(tmp_path, TREE, [component])
    for resource in resources:
        validate(resource)
    monitor = one(resources, kind, "gcdtrav")
    assert monitor["metadata"]["namespace"] == "gcdtrav"
    endpoints = monitor["spec"]["endpoints" if kind == "ServiceMonitor" else "podMetricsEndpoints"]
    assert [(e["port"], e["path"]) for e in endpoints] == [("http", "/metrics")]
    deployment = one(resources, "Deployment", "gcdtrav")
    if kind == "ServiceMonitor":
        service = one(resources, "Service", "gcdtrav-metrics")
        assert monitor["spec"]["selector"]["matchLabels"].items() <= service["metadata"]["labels"].items()
        assert endpoints[0]["port"] in [p["name"] for p in service["spec"]["ports"]]
    else:
        pod_labels = deployment["spec"]["template"]["metadata"]["labels"]
        assert monitor["spec"]["selector"]["matchLabels"].items() <= pod_labels.items()
        ports = deployment["spec"]["template"]["spec"]["containers"][0]["ports"]
        assert endpoints[0]["port"] in [p["name"] for p in ports]
    broken = copy.deepcopy(monitor)
    broken["spec"]["endpoint"] = broken["spec"].pop("endpoints" if kind == "ServiceMonitor" else "podMetricsEndpoints")
    with pytest.raises(jsonschema.ValidationError):
        validate(broken)


@pytest.mark.parametrize("base", ["", "hpa"])
def test_the_fleet_store_on_cloudnative_pg(base: str, tmp_path: Path) -> None:
    """The CloudNativePG Cluster validates against its CRD schema; the service's store URL names the Cluster's
    read-write Service (<cluster>-rw), database and owner, and its password file is the `password` key of the
    Secret CloudNativePG writes (<cluster>-app); no password in the environment."""
    import copy

    import jsonschema

    resources = overlay(tmp_path, TREE / base if base else TREE, ["postgresql"])
    for resource in resources:
        validate(resource)
    cluster = one(resources, "Cluster", "gcdtrav-db")
    assert cluster["spec"]["instances"] >= 2
    pod = one(resources, "Deployment", "gcdtrav")["spec"]["template"]["spec"]
    env = {e["name"]: e.get("value") for e in pod["containers"][0]["env"]}
    assert not [name for name in env if "PASSWORD" in name and name != "GCDTRAV_STORE__PASSWORD_FILE"]
    from urllib.parse import urlsplit

    url = urlsplit(env["GCDTRAV_STORE__URL"])
    initdb = cluster["spec"]["bootstrap"]["initdb"]
    assert url.hostname == f"{cluster['metadata']['name']}-rw" and url.port == 5432 and url.password is None
    assert (url.path.lstrip("/"), url.username) == (initdb["database"], initdb["owner"])
    password_file = Path(env["GCDTRAV_STORE__PASSWORD_FILE"])
    mount = next(m for m in pod["containers"][0]["volumeMounts"] if m["mountPath"] == str(password_file.parent))
    secret = next(v for v in pod["volumes"] if v["name"] == mount["name"])["secret"]
    assert secret["secretName"] == f"{cluster['metadata']['name']}-app"
    assert secret["items"] == [{"key": "password", "path": password_file.name}]
    from gcdtrav.schemas.settings import ServiceSettings, load_settings

    if "store" in ServiceSettings.model_fields:  # the store: settings section (issue 46)
        (tmp_path / "empty.yaml").write_text("{}\n", "utf-8")
        literal = {k: v for k, v in env.items() if k.startswith("GCDTRAV_STORE") and v is not None}
        settings = load_settings(tmp_path / "empty.yaml", environ=literal)
        assert settings.store.url == env["GCDTRAV_STORE__URL"]  # type: ignore[attr-defined]
        assert settings.store.password_file == password_file  # type: ignore[attr-defined]
    broken = copy.deepcopy(cluster)
    broken["spec"]["instance"] = broken["spec"].pop("instances")
    with pytest.raises(jsonschema.ValidationError):
        validate(broken)
