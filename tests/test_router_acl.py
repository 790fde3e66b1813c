"""The router's per-cell access control (``protocol.session.Cell``, ``router_access_control``):
parsing ``--cell`` and the rules it makes. Real routers and certificates enforcing them:
``tests/test_net_router.py``."""

from __future__ import annotations

import json

import pytest
import zenoh

from protocol import ProtocolError
from protocol.session import COMMAND_TOPICS, TELEMETRY_TOPICS, Cell, router_access_control


def test_a_cell_names_its_work_site_operators_and_viewers() -> None:
    cell = Cell.parse("cell-a=ws-a:op-1,op-2:tv,op-1")
    assert cell == Cell("cell-a", "ws-a", ("op-1", "op-2"), ("tv", "op-1"))
    assert cell.members == ("ws-a", "op-1", "op-2", "tv")
    assert Cell.parse("cell-b=ws-b:op").viewers == ()


@pytest.mark.parametrize(
    "text",
    ["cell-a", "cell-a=ws", "cell-a=ws:", "cell-a=:op", "=ws:op", "a=ws:op:tv:x", "a b=ws:op"],
)
def test_a_malformed_cell_is_refused_saying_the_form(text: str) -> None:
    with pytest.raises(ProtocolError, match=r"SITE=WORK_SITE_CN:OPERATOR_CN|site"):
        Cell.parse(text)


def _allowed(acl: dict, name: str, flow: str, message: str) -> set[str]:
    """The key expressions the rules let certificate ``name`` use for ``message`` on ``flow``."""
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    keys: set[str] = set()
    for policy in acl["policies"]:
        if not any(name in subjects[s]["cert_common_names"] for s in policy["subjects"]):
            continue
        for rule in (rules[r] for r in policy["rules"]):
            if flow in rule["flows"] and message in rule["messages"]:
                keys.update(rule["key_exprs"])
    return keys


def test_each_certificate_sees_and_puts_only_what_its_cells_allow() -> None:
    acl = router_access_control([Cell.parse("cell-a=ws-a:op-a:tv"), Cell.parse("cell-b=ws-b:op-b")])
    assert acl["default_permission"] == "deny"
    a, b = "telerobot/cell-a", "telerobot/cell-b"
    assert _allowed(acl, "op-a", "ingress", "put") == {f"{a}/{t}" for t in COMMAND_TOPICS}
    assert _allowed(acl, "ws-a", "ingress", "put") == {f"{a}/{t}" for t in TELEMETRY_TOPICS}
    assert _allowed(acl, "tv", "ingress", "put") == set()  # a viewer only watches
    for name, cells in (("op-a", {a}), ("tv", {a}), ("ws-b", {b}), ("op-b", {b})):
        watched = {f"{c}/**" for c in cells}
        assert _allowed(acl, name, "ingress", "declare_subscriber") == watched
        assert _allowed(acl, name, "egress", "put") == watched
        assert _allowed(acl, name, "egress", "liveliness_token") == watched
    assert _allowed(acl, "stranger", "egress", "put") == set()
    # zenoh takes the rules as a router's config.
    config = zenoh.Config()
    config.insert_json5("access_control", json.dumps(acl))


def test_cells_must_be_given_and_distinct() -> None:
    with pytest.raises(ProtocolError, match="at least one cell"):
        router_access_control([])
    with pytest.raises(ProtocolError, match="given twice"):
        router_access_control([Cell.parse("a=ws:op"), Cell.parse("a=ws:op2")])


def test_a_meshed_router_relays_every_cell_both_ways() -> None:
    acl = router_access_control([Cell.parse("cell-a=ws-a:op-a")], relays=["router"])
    for flow in ("ingress", "egress"):
        for message in ("put", "declare_subscriber", "liveliness_token"):
            assert _allowed(acl, "router", flow, message) == {"telerobot/**"}
    assert _allowed(acl, "op-a", "ingress", "put") == {
        f"telerobot/cell-a/{t}" for t in COMMAND_TOPICS
    }
