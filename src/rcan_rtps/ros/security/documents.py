"""The DDS-Security XML documents of an SROS2 keystore: governance and permissions.

Governance is SROS2's default (every topic authenticated, discovery and liveliness
encrypted, data encrypted, unauthenticated participants refused). Permissions come from an
SROS2 policy (`<policy version="0.2.0"><enclaves><enclave path=…><profiles><profile ns node>`
with `topics publish/subscribe`, `services request/reply`, `actions call/execute`), turned
into DDS topic names as ROS 2 mangles them (rt/ topics, rq/…Request and rr/…Reply for
services, the five topics of an action), plus `ros_discovery_info`, which every node of the
Cyclone and Fast DDS RMWs (and rcan-rtps) reads and writes.
"""

from __future__ import annotations

import datetime
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from .errors import PolicyError

_XSI = "http://www.w3.org/2001/XMLSchema-instance"
_SCHEMA = "http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_{}.xsd"
ET.register_namespace("xsi", _XSI)

POLICY_VERSION = "0.2.0"
_ACTION_SERVICES = ("cancel_goal", "get_result", "send_goal")
_ACTION_TOPICS = ("feedback", "status")
# A policy element's attributes and what each grants: (attribute, publish?) per kind of name.
_KINDS = {
    "topics": ("topic", {"publish", "subscribe"}),
    "services": ("service", {"request", "reply"}),
    "actions": ("action", {"call", "execute"}),
}


def _pretty(root: ET.Element) -> bytes:
    ET.indent(root, space="  ")
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root) + b"\n"


def _sub(parent: ET.Element, tag: str, text: str | None = None) -> ET.Element:
    child = ET.SubElement(parent, tag)
    if text is not None:
        child.text = text
    return child


def _dds_root(kind: str) -> ET.Element:
    return ET.Element("dds", {f"{{{_XSI}}}noNamespaceSchemaLocation": _SCHEMA.format(kind)})


def governance_xml(domain_id: int) -> bytes:
    """SROS2's default governance for one domain."""
    root = _dds_root("governance")
    rule = _sub(_sub(root, "domain_access_rules"), "domain_rule")
    _sub(_sub(rule, "domains"), "id", str(domain_id))
    for tag, text in (("allow_unauthenticated_participants", "false"),
                      ("enable_join_access_control", "true"),
                      ("discovery_protection_kind", "ENCRYPT"),
                      ("liveliness_protection_kind", "ENCRYPT"),
                      ("rtps_protection_kind", "SIGN")):
        _sub(rule, tag, text)
    topic_rule = _sub(_sub(rule, "topic_access_rules"), "topic_rule")
    for tag, text in (("topic_expression", "*"),
                      ("enable_discovery_protection", "true"),
                      ("enable_liveliness_protection", "true"),
                      ("enable_read_access_control", "true"),
                      ("enable_write_access_control", "true"),
                      ("metadata_protection_kind", "ENCRYPT"),
                      ("data_protection_kind", "ENCRYPT")):
        _sub(topic_rule, tag, text)
    return _pretty(root)


@dataclass
class Rule:
    """DDS topic names (globs) an enclave may publish and subscribe, under one qualifier."""

    publish: set[str] = field(default_factory=set)
    subscribe: set[str] = field(default_factory=set)


@dataclass
class Grant:
    """What one enclave (its certificate's CN) is allowed and denied."""

    enclave: str
    allow: Rule = field(default_factory=Rule)
    deny: Rule = field(default_factory=Rule)


def default_policy(enclave: str) -> bytes:
    """SROS2's default policy: the enclave may use every topic, service and action."""
    return (f'<policy version="{POLICY_VERSION}"><enclaves><enclave path="{enclave}">'
            '<profiles><profile ns="/" node="default">'
            '<topics publish="ALLOW" subscribe="ALLOW"><topic>/*</topic></topics>'
            '<services reply="ALLOW" request="ALLOW"><service>/*</service></services>'
            '<actions call="ALLOW" execute="ALLOW"><action>/*</action></actions>'
            '</profile></profiles></enclave></enclaves></policy>').encode()


def _qualified(name: str, namespace: str, node: str) -> str:
    """A policy name made absolute as ROS resolves it: `/x` as is, `~/x` under the node,
    anything else under the profile's namespace."""
    if name.startswith("/"):
        return name
    ns = namespace if namespace.endswith("/") else namespace + "/"
    if name.startswith("~"):
        return ns + node + name[1:]
    return ns + name


def _dds_names(kind: str, name: str, grants: str) -> tuple[list[str], list[str]]:
    """(published, subscribed) DDS topics for a policy name of `kind` granted `grants`."""
    if kind == "topics":
        return ([f"rt{name}"], []) if grants == "publish" else ([], [f"rt{name}"])
    if kind == "services":
        request, reply = f"rq{name}Request", f"rr{name}Reply"
        return ([request], [reply]) if grants == "request" else ([reply], [request])
    requests = [f"rq{name}/_action/{s}Request" for s in _ACTION_SERVICES]
    replies = [f"rr{name}/_action/{s}Reply" for s in _ACTION_SERVICES]
    topics = [f"rt{name}/_action/{t}" for t in _ACTION_TOPICS]
    return (requests, replies + topics) if grants == "call" else (replies + topics, requests)


def _profile_rules(profile: ET.Element, grant: Grant) -> None:
    namespace = profile.get("ns", "/")
    node = profile.get("node", "")
    for group in profile:
        if group.tag not in _KINDS:
            raise PolicyError(f"profile ns={namespace!r} node={node!r}: unknown element "
                              f"<{group.tag}> (expected topics, services or actions)")
        item, allowed = _KINDS[group.tag]
        for grants, qualifier in group.attrib.items():
            if grants not in allowed or qualifier not in ("ALLOW", "DENY"):
                raise PolicyError(f"<{group.tag} {grants}={qualifier!r}>: expected "
                                  f"{' or '.join(sorted(allowed))} = ALLOW or DENY")
            rule = grant.allow if qualifier == "ALLOW" else grant.deny
            for element in group:
                if element.tag != item or not (element.text or "").strip():
                    raise PolicyError(f"<{group.tag}> holds <{element.tag}>: expected a "
                                      f"non-empty <{item}>")
                name = _qualified(element.text.strip(), namespace, node)  # type: ignore[union-attr]
                published, subscribed = _dds_names(group.tag, name, grants)
                rule.publish.update(published)
                rule.subscribe.update(subscribed)


def _enclaves(policy: ET.Element) -> Iterator[ET.Element]:
    if policy.tag != "policy":
        raise PolicyError(f"not an SROS2 policy (root <{policy.tag}>, expected <policy>)")
    yield from policy.iterfind("enclaves/enclave")


def read_policy(data: bytes, enclave: str, source: str = "policy") -> Grant:
    """The grant of `enclave` in an SROS2 policy document (PolicyError when it has none)."""
    try:
        policy = ET.fromstring(data)
    except ET.ParseError as e:
        raise PolicyError(f"{source}: not XML ({e})") from e
    found = [e for e in _enclaves(policy) if e.get("path") == enclave]
    if not found:
        known = ", ".join(sorted(str(e.get("path")) for e in _enclaves(policy))) or "none"
        raise PolicyError(f"{source}: no enclave {enclave!r} (it has: {known})")
    grant = Grant(enclave)
    for profile in found[0].iterfind("profiles/profile"):
        _profile_rules(profile, grant)
    return grant


def read_policy_file(path: Path, enclave: str) -> Grant:
    try:
        data = path.read_bytes()
    except OSError as e:
        raise PolicyError(f"cannot read the policy {path}: {e.strerror}") from e
    return read_policy(data, enclave, str(path))


def _rule(parent: ET.Element, tag: str, domain_id: int, publish: Iterable[str],
          subscribe: Iterable[str]) -> None:
    rule = _sub(parent, tag)
    _sub(_sub(rule, "domains"), "id", str(domain_id))
    for direction, names in (("publish", publish), ("subscribe", subscribe)):
        names = sorted(set(names))
        if names:
            topics = _sub(_sub(rule, direction), "topics")
            for name in names:
                _sub(topics, "topic", name)


def _dds_time(moment: datetime.datetime) -> str:
    return moment.astimezone(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def permissions_xml(grant: Grant, domain_id: int, not_before: datetime.datetime,
                    not_after: datetime.datetime) -> bytes:
    """The DDS permissions document of one grant, valid as long as the enclave's
    certificate (SROS2 takes the same window). Denials come first: DDS takes the first
    rule that matches."""
    root = _dds_root("permissions")
    grant_element = _sub(_sub(root, "permissions"), "grant", None)
    grant_element.set("name", grant.enclave)
    _sub(grant_element, "subject_name", f"CN={grant.enclave}")
    validity = _sub(grant_element, "validity")
    _sub(validity, "not_before", _dds_time(not_before))
    _sub(validity, "not_after", _dds_time(not_after))
    if grant.deny.publish or grant.deny.subscribe:
        _rule(grant_element, "deny_rule", domain_id, grant.deny.publish, grant.deny.subscribe)
    if grant.allow.publish or grant.allow.subscribe:
        _rule(grant_element, "allow_rule", domain_id, grant.allow.publish,
              grant.allow.subscribe)
    _rule(grant_element, "allow_rule", domain_id, ["ros_discovery_info"],
          ["ros_discovery_info"])
    _sub(grant_element, "default", "DENY")
    return _pretty(root)
