"""GET /api/metrics: Prometheus text, counting exactly what the audit log recorded."""

from __future__ import annotations

from tests.api.apihelpers import Api, auth


async def test_metrics_count_audited_decisions(api: Api) -> None:
    ok = await api.http.post("/api/command", headers=auth("planner"),
                             json={"action": "move", "params": {"linear_x": 0.2}})
    assert ok.status == 200
    refused = await api.http.post("/api/command", headers=auth("planner"),
                                  json={"action": "move", "params": {"linear_x": 99.0}})
    assert refused.status == 409
    resp = await api.http.get("/api/metrics", headers=auth("viewer"))
    assert resp.status == 200 and resp.content_type == "text/plain"
    text = await resp.text()
    assert ('rcan_audit_entries_total{action="move",event="COMMAND_DISPATCHED",'
            'outcome="executed"} 1.0') in text
    assert ('rcan_audit_entries_total{action="move",event="COMMAND_REJECTED",'
            'outcome="safety_violation"} 1.0') in text
    assert "rcan_command_seconds_count 2.0" in text
    assert "rcan_estop_latched 0.0" in text and "rcan_pending_approvals 0.0" in text


async def test_metrics_need_credentials(api: Api) -> None:
    assert (await api.http.get("/api/metrics")).status == 401
