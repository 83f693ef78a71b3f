"""``/healthz`` and ``/metrics`` (Prometheus text format)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from eventocc.server.api.deps import LiveDep

router = APIRouter(tags=["health"])


@router.get("/healthz")
def health(live: LiveDep) -> dict[str, Any]:
    live.receptions.totals()  # raises (500) if the database is unreachable
    return {"status": "ok", "receivers": len(live.receivers), "dashboards": live.hub.viewer_count}


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(live: LiveDep) -> str:
    received, received_bytes = live.receptions.totals()
    samples = [
        ("eventocc_receivers_connected", "gauge", "Receiver daemons connected now.",
         len(live.receivers)),
        ("eventocc_dashboard_clients", "gauge", "Dashboard viewers connected now.",
         live.hub.viewer_count),
        ("eventocc_frames_decoded_total", "counter", "Data frames receivers decoded.",
         live.frames_decoded),
        ("eventocc_goodput_bits_per_second", "gauge",
         "Bits of verified messages received per second over the last minute.",
         live.goodput_bps()),
        ("eventocc_receptions_total", "counter", "Verified messages received.", received),
        ("eventocc_received_bytes_total", "counter", "Bytes of verified messages received.",
         received_bytes),
        ("eventocc_reports_rejected_total", "counter", "Receiver reports failing the schema.",
         live.reports_rejected),
        ("eventocc_dashboard_updates_dropped_total", "counter",
         "Updates slow dashboards lost (decimated).", live.hub.dropped),
        ("eventocc_dashboard_evictions_total", "counter", "Stalled dashboards dropped.",
         live.hub.evicted),
    ]  # fmt: skip
    return "".join(
        f"# HELP {name} {help_}\n# TYPE {name} {kind}\n{name} {value}\n"
        for name, kind, help_, value in samples
    )
