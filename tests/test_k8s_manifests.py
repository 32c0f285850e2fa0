"""The Kubernetes manifests (compose/k8s/) and the settings the Swarm stack (compose/stack.yaml) gives its tasks,
checked without a cluster.

Every manifest is loaded into the `kubernetes` client's models (ApiClient's deserializer, with its client-side
validation of required fields) and serialised back: the round trip must give the document again, so a key the
API does not know (a typo: `servicename`, `matchlabel`) fails here instead of being dropped by `kubectl apply`.
Then the parts that must fit together: the StatefulSet's serviceName is the headless Service (clusterIP None),
every selector matches its pod template's labels and no other workload's, Services target named container
ports, the token Secret is the one mounted where HAA_TOKEN_FILE points, every `$(VAR)` is defined before it is
used. Finally the pods' environment (downward API resolved for sample pod names) goes through haa-hostd's own
settings loader (`haa.hostd.daemon.load_settings`): every HAA_* variable is one the daemon reads, and the core
list names the StatefulSet's pods at their stable DNS names. The same loader checks a core and a host task of
the Swarm stack with its `{{.Task.Slot}}` templates filled in. ≈1 s.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from kubernetes.client import ApiClient

from haa.hostd import daemon

REPO = Path(__file__).resolve().parents[1]
K8S = REPO / "compose" / "k8s"
STACK = REPO / "compose" / "stack.yaml"
NS = "haa"


def load_docs() -> list[dict[str, Any]]:
    docs = []
    for f in sorted(K8S.glob("*.yaml")):
        docs += [d for d in yaml.safe_load_all(f.read_text()) if d]
    return docs


def to_model(api: ApiClient, doc: dict[str, Any]) -> Any:
    version = doc["apiVersion"].split("/")[-1].capitalize()  # v1 -> V1
    return api._ApiClient__deserialize(doc, f"{version}{doc['kind']}")  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def objs() -> dict[tuple[str, str], Any]:
    api = ApiClient()
    out = {}
    for doc in load_docs():
        model = to_model(api, doc)
        back = api.sanitize_for_serialization(model)
        assert back == doc, f"{doc['kind']} {doc['metadata']['name']}: keys the API does not know, or lost"
        out[(doc["kind"], doc["metadata"]["name"])] = model
    return out


def test_every_object_is_there_in_the_namespace(objs: dict[tuple[str, str], Any]) -> None:
    assert sorted(objs) == sorted([
        ("Namespace", NS), ("Secret", "haa-token"), ("Service", "haa-core"), ("StatefulSet", "haa-core"),
        ("Deployment", "haa-host"), ("Service", "haa-sim"), ("Deployment", "haa-sim"),
    ])
    for (kind, _), o in objs.items():
        if kind != "Namespace":
            assert o.metadata.namespace == NS


def workloads(objs: dict[tuple[str, str], Any]) -> dict[str, Any]:
    return {name: o for (kind, name), o in objs.items() if kind in ("StatefulSet", "Deployment")
            and name != "haa-sim"} | {"haa-sim": objs[("Deployment", "haa-sim")]}


def matches(selector: dict[str, str], labels: dict[str, str]) -> bool:
    return all(labels.get(k) == v for k, v in selector.items())


def test_selectors_headless_service_and_ports(objs: dict[tuple[str, str], Any]) -> None:
    ws = workloads(objs)
    for name, w in ws.items():
        labels = w.spec.template.metadata.labels
        assert matches(w.spec.selector.match_labels, labels), name
        for other, o in ws.items():  # a workload's selector must not take another's pods
            if other != name:
                assert not matches(w.spec.selector.match_labels, o.spec.template.metadata.labels), (name, other)
    core = objs[("StatefulSet", "haa-core")]
    headless = objs[("Service", "haa-core")]
    assert core.spec.service_name == headless.metadata.name
    assert headless.spec.cluster_ip == "None" and headless.spec.publish_not_ready_addresses
    assert core.spec.replicas == 3 and core.spec.update_strategy.type == "RollingUpdate"
    assert core.spec.volume_claim_templates[0].metadata.name == "data"
    for svc, w in ((headless, core), (objs[("Service", "haa-sim")], objs[("Deployment", "haa-sim")])):
        assert matches(svc.spec.selector, w.spec.template.metadata.labels)
        assert not any(matches(svc.spec.selector, o.spec.template.metadata.labels) for o in ws.values() if o is not w)
        port_names = {p.name for c in w.spec.template.spec.containers for p in c.ports}
        assert {p.target_port for p in svc.spec.ports} <= port_names, svc.metadata.name


def resolve_env(container: Any, fields: dict[str, str]) -> dict[str, str]:
    """The container's environment as the kubelet makes it: downward API fields, $(VAR) expanded."""
    env: dict[str, str] = {}
    for e in container.env or []:
        if e.value_from is not None:
            env[e.name] = fields[e.value_from.field_ref.field_path]
            continue
        for ref in re.findall(r"\$\((\w+)\)", e.value):
            assert ref in env, f"{e.name} uses $({ref}) before it is defined"
        env[e.name] = re.sub(r"\$\((\w+)\)", lambda m: env[m.group(1)], e.value)
    return env


def settings_of(env: dict[str, str], args: list[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                token_path: str) -> daemon.HostSettings:
    """haa-hostd's settings from this environment, the token file moved under tmp_path."""
    for k in [k for k in list(os.environ) if k.startswith("HAA_")]:
        monkeypatch.delenv(k)
    (tmp_path / "token").write_text("0" * 64 + "\n")
    assert env["HAA_TOKEN_FILE"] == token_path
    for k, v in {**env, "HAA_TOKEN_FILE": str(tmp_path / "token")}.items():
        monkeypatch.setenv(k, v)
    read = {"HAA_" + o.upper() for o in daemon._OPTIONS}
    assert {k for k in env if k.startswith("HAA_")} <= read, f"variables haa-hostd does not read: {set(env) - read}"
    return daemon.load_settings(args)


def test_pods_environment_is_what_haa_hostd_reads(objs: dict[tuple[str, str], Any], monkeypatch: pytest.MonkeyPatch,
                                                 tmp_path: Path) -> None:
    core = objs[("StatefulSet", "haa-core")]
    secret = objs[("Secret", "haa-token")]
    pods = [f"{core.metadata.name}-{i}" for i in range(core.spec.replicas)]
    for w, pod in ((core, pods[1]), (objs[("Deployment", "haa-host")], "haa-host-5d8f7c9b6-x2x4k")):
        spec = w.spec.template.spec
        c = spec.containers[0]
        mounts = {m.name: m.mount_path for m in c.volume_mounts}
        vols = {v.name: v for v in spec.volumes}
        assert vols["token"].secret.secret_name == secret.metadata.name
        token_path = f"{mounts['token']}/{next(iter(secret.string_data))}"
        env = resolve_env(c, {"metadata.name": pod, "status.podIP": "10.244.1.7"})
        s = settings_of(env, list(c.args), monkeypatch, tmp_path, token_path)
        assert s.name == pod and s.log_stderr and s.metrics_port == 9400
        assert s.core == [(p, f"{p}.{core.spec.service_name}:7000") for p in pods]
        assert str(s.data_dir) == mounts["data"]
        assert s.advertise == (f"{pod}.haa-core:7000" if w is core else "10.244.1.7:7000")


def stack_env(svc: dict[str, Any], slot: int) -> dict[str, str]:
    env = {k: str(v) for k, v in svc["environment"].items()}
    return {k: v.replace("{{.Task.Slot}}", str(slot)) for k, v in env.items()
            if not v.startswith("${")}  # ${VAR:-} interpolations are empty by default


def test_swarm_stack_tasks(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    stack = yaml.safe_load(STACK.read_text())
    svcs = stack["services"]
    for svc, slot, name in (("core", 2, "core2"), ("host", 4, "host4")):
        s = svcs[svc]
        assert s["hostname"].replace("{{.Task.Slot}}", str(slot)) == name  # the DNS alias peers dial
        st = settings_of(stack_env(s, slot), s["command"], monkeypatch, tmp_path, "/run/secrets/haa_token")
        assert st.name == name and st.core == [(f"core{i}", f"core{i}:7000") for i in (1, 2, 3)]
        assert s["secrets"] == ["haa_token"] and "haa_token" in stack["secrets"]
        vol = s["volumes"][0].split(":")
        assert vol[1] == str(st.data_dir) and "{{.Task.Slot}}" in stack["volumes"][vol[0]]["name"]
        dep = s["deploy"]
        assert dep["update_config"]["parallelism"] == 1 and dep["update_config"]["order"] == "stop-first"
        assert dep["restart_policy"]["condition"] == "on-failure"
    assert svcs["core"]["deploy"]["replicas"] == 3
    assert svcs["sim"]["entrypoint"][-1] == "haa-sim"
