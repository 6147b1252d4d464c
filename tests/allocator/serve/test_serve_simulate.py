"""``agv serve --simulate``: the simulator's AGVs report, follow the plan and deliver; a
restart on the same database carries on where it stopped."""

from __future__ import annotations

import time

import httpx

import sim
from allocator.serve.process import ServiceProcess


def test_simulated_fleet_delivers_and_survives_a_restart(tmp_path) -> None:
    w = sim.warehouse_floor(20)
    args = ["--simulate", "warehouse-20", "--method", "fifo"]
    svc = ServiceProcess(tmp_path, args).start()
    try:
        with httpx.Client(base_url=svc.url, headers=svc.headers, timeout=10) as c:
            plan = c.get("/v1/plan").json()
            assert [a["id"] for a in plan["agents"]] == [f"sim-{i:02d}" for i in range(20)]
            orders = [{"id": f"s-{k}", "pickup": w.pickups[(5 * k) % len(w.pickups)].tolist(),
                       "dropoff": w.stations[k % len(w.stations)].tolist()} for k in range(8)]
            assert c.post("/v1/orders", json={"orders": orders}).status_code == 201
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                stats = c.get("/v1/plan").json()["stats"]
                if stats["delivered"] >= 4:
                    break
                time.sleep(0.5)
            assert stats["delivered"] >= 4, stats
            before = {a["id"]: a["position"] for a in c.get("/v1/plan").json()["agents"]}
        svc.kill()
        svc2 = ServiceProcess(tmp_path, args).start()
        try:
            with httpx.Client(base_url=svc2.url, headers=svc2.headers, timeout=10) as c:
                plan = c.get("/v1/plan").json()
                assert plan["stats"]["accepted"] == 8
                assert plan["stats"]["delivered"] >= stats["delivered"]
                # The simulated AGVs start where the database last saw them (within the
                # second between stored positions, at about 1.2 units per second).
                for a in plan["agents"]:
                    x0, y0 = before[a["id"]]
                    assert abs(a["position"][0] - x0) + abs(a["position"][1] - y0) < 3.0
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:
                    stats = c.get("/v1/plan").json()["stats"]
                    if stats["delivered"] == 8:
                        break
                    time.sleep(0.5)
                assert stats["delivered"] == 8, stats
        finally:
            svc2.stop()
    finally:
        svc.stop()
