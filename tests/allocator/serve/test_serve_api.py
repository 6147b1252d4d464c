"""The HTTP API against a real uvicorn: the life of an order, idempotency, every error."""

from __future__ import annotations

import itertools
import time

import httpx

import sim

W = sim.warehouse_floor(20)
PICK = [round(float(v), 4) for v in W.pickups[0]]
PICK2 = [round(float(v), 4) for v in W.pickups[5]]
DROP = [round(float(v), 4) for v in W.stations[1]]
_ids = itertools.count()


def uid(prefix: str) -> str:
    return f"{prefix}-{time.time_ns()}-{next(_ids)}"


def wait_for(pred, timeout: float = 60.0, every: float = 0.05):
    # A generous bound: it returns as soon as the condition holds, and the server's planning
    # loop can be slow on a loaded 2-core machine (10 s was not always enough).
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(every)
    raise AssertionError("condition not met in time")


def plan_entry(client: httpx.Client, agent: str) -> dict:
    return next(a for a in client.get("/v1/plan").json()["agents"] if a["id"] == agent)


def test_whole_life_of_an_order(client: httpx.Client) -> None:
    agv = uid("agv")
    r = client.put(f"/v1/agents/{agv}", json={"position": DROP, "status": "idle"})
    assert r.status_code == 201, r.text
    assert r.json()["status"] == "idle"
    oid = uid("order")
    r = client.post("/v1/orders", json={"id": oid, "pickup": PICK, "dropoff": DROP,
                                        "priority": 2})
    assert r.status_code == 201, r.text
    assert r.json()["status"] == "open"
    # The dispatcher gives it to the only free AGV, with a path along the aisles.
    entry = wait_for(lambda: (e := plan_entry(client, agv))["order"] == oid and e["path"]
                     and e)
    assert entry["leg"] == "pickup"
    assert entry["path"][0] == DROP and entry["path"][-1] == PICK
    assert client.get(f"/v1/orders/{oid}").json()["status"] == "assigned"
    assert client.get(f"/v1/orders/{oid}").json()["agent"] == agv
    # The AGV drives there, picks it up, delivers it.
    client.put(f"/v1/agents/{agv}", json={"position": PICK, "status": "busy"})
    r = client.post(f"/v1/agents/{agv}/events", json={"type": "picked_up", "order": oid})
    assert r.status_code == 200, r.text
    assert r.json()["loaded"] is True
    order = client.get(f"/v1/orders/{oid}").json()
    assert order["status"] == "loaded" and order["picked_up"] is not None
    entry = wait_for(lambda: (e := plan_entry(client, agv))["leg"] == "dropoff" and e)
    assert entry["order"] == oid
    r = client.post(f"/v1/agents/{agv}/events", json={"type": "delivered", "order": oid})
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "idle" and r.json()["order"] is None
    order = client.get(f"/v1/orders/{oid}").json()
    assert order["status"] == "delivered" and order["delivered"] >= order["picked_up"]
    stats = client.get("/v1/plan").json()["stats"]
    assert stats["delivered"] >= 1 and stats["wait_mean_s"] is not None
    # Out of service, then back.
    r = client.post(f"/v1/agents/{agv}/events", json={"type": "fault"})
    assert r.json()["status"] == "broken"
    r = client.post(f"/v1/agents/{agv}/events", json={"type": "repaired"})
    assert r.json()["status"] == "idle"
    client.put(f"/v1/agents/{agv}", json={"position": DROP, "status": "charging"})


def test_a_fault_returns_the_order_to_the_pool(client: httpx.Client) -> None:
    a, b = uid("agv"), uid("agv")
    client.put(f"/v1/agents/{a}", json={"position": PICK2, "status": "idle"})
    oid = uid("order")
    client.post("/v1/orders", json={"id": oid, "pickup": PICK2, "dropoff": DROP})
    wait_for(lambda: client.get(f"/v1/orders/{oid}").json()["agent"] == a)
    client.post(f"/v1/agents/{a}/events", json={"type": "fault"})
    client.put(f"/v1/agents/{b}", json={"position": DROP, "status": "idle"})
    wait_for(lambda: client.get(f"/v1/orders/{oid}").json()["agent"] == b)
    client.delete(f"/v1/orders/{oid}")
    client.post(f"/v1/agents/{a}/events", json={"type": "repaired"})
    client.put(f"/v1/agents/{a}", json={"position": DROP, "status": "charging"})
    client.put(f"/v1/agents/{b}", json={"position": DROP, "status": "charging"})


def test_same_id_is_one_order(client: httpx.Client, service) -> None:
    oid = uid("dup")
    body = {"id": oid, "pickup": PICK, "dropoff": DROP, "priority": 1}
    first = client.post("/v1/orders", json=body)
    again = client.post("/v1/orders", json=body)
    assert first.status_code == 201 and again.status_code == 200
    assert first.json()["created"] == again.json()["created"]
    r = client.post("/v1/orders", json=body | {"priority": 3})
    assert r.status_code == 409 and oid in r.json()["detail"]
    r = client.post("/v1/orders", json=body | {"dropoff": [DROP[0], DROP[1] + 0.8]})
    assert r.status_code == 409
    import sqlite3

    with sqlite3.connect(service.db) as db:
        assert db.execute("SELECT COUNT(*) FROM orders WHERE id=?", (oid,)).fetchone()[0] == 1
    client.delete(f"/v1/orders/{oid}")


def test_batch_all_or_none(client: httpx.Client) -> None:
    ids = [uid("batch") for _ in range(3)]
    orders = [{"id": i, "pickup": PICK, "dropoff": DROP} for i in ids]
    r = client.post("/v1/orders", json={"orders": orders})
    assert r.status_code == 201 and [o["id"] for o in r.json()["orders"]] == ids
    r = client.post("/v1/orders", json={"orders": orders})
    assert r.status_code == 200
    bad = orders + [{"id": uid("batch"), "pickup": [-5, 1], "dropoff": DROP}]
    r = client.post("/v1/orders", json={"orders": bad})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "orders", 3, "pickup"]
    for i in ids:
        assert client.delete(f"/v1/orders/{i}").json()["status"] == "withdrawn"


def test_withdraw(client: httpx.Client) -> None:
    oid = uid("w")
    client.post("/v1/orders", json={"id": oid, "pickup": PICK, "dropoff": DROP})
    r = client.delete(f"/v1/orders/{oid}")
    assert r.status_code == 200 and r.json()["status"] == "withdrawn"
    assert client.delete(f"/v1/orders/{oid}").status_code == 200  # a repeat is harmless
    assert client.get(f"/v1/orders/{oid}").json()["status"] == "withdrawn"
    # Not after pickup.
    agv, oid = uid("agv"), uid("w")
    client.put(f"/v1/agents/{agv}", json={"position": PICK, "status": "idle"})
    client.post("/v1/orders", json={"id": oid, "pickup": PICK, "dropoff": DROP})
    assert client.post(f"/v1/agents/{agv}/events",
                       json={"type": "picked_up", "order": oid}).status_code == 200
    r = client.delete(f"/v1/orders/{oid}")
    assert r.status_code == 409 and "picked up" in r.json()["detail"]
    client.post(f"/v1/agents/{agv}/events", json={"type": "delivered", "order": oid})
    assert client.delete(f"/v1/orders/{oid}").status_code == 409
    client.put(f"/v1/agents/{agv}", json={"position": PICK, "status": "charging"})


def test_401_without_the_key(service) -> None:
    url = service.url
    assert httpx.get(url + "/healthz").status_code == 200
    for method, path in (("GET", "/v1/plan"), ("GET", "/openapi.json"),
                         ("POST", "/v1/orders"), ("GET", "/v1/events"),
                         ("PUT", "/v1/agents/a1"), ("DELETE", "/v1/orders/x"),
                         ("GET", "/docs")):
        for headers in ({}, {"Authorization": "Bearer wrong-key-wrong-key"},
                        {"Authorization": service.key}, {"Authorization": "Basic abc"}):
            r = httpx.request(method, url + path, headers=headers)
            assert r.status_code == 401, (method, path, headers)
            assert r.headers["www-authenticate"] == "Bearer"


def test_413_body_and_list_limits(client: httpx.Client) -> None:
    r = client.post("/v1/orders", content=b"{" + b" " * (300 * 1024) + b"}",
                    headers={"content-type": "application/json"})
    assert r.status_code == 413
    orders = [{"id": f"big-{k}", "pickup": PICK, "dropoff": DROP} for k in range(501)]
    r = client.post("/v1/orders", json={"orders": orders})
    assert r.status_code == 413 and "500" in r.json()["detail"]

    def chunks():  # no Content-Length: counted as it streams
        for _ in range(40):
            yield b" " * 10_000

    r = client.post("/v1/orders", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_422_names_the_field(client: httpx.Client) -> None:
    def loc(r: httpx.Response) -> list:
        assert r.status_code == 422, r.text
        return r.json()["detail"][0]["loc"]

    ok = {"id": uid("v"), "pickup": PICK, "dropoff": DROP}
    assert loc(client.post("/v1/orders", json={k: v for k, v in ok.items() if k != "id"})
               ) == ["body", "id"]
    assert loc(client.post("/v1/orders", json=ok | {"pickup": [1.0]})) == ["body", "pickup"]
    assert loc(client.post("/v1/orders", json=ok | {"pickup": [100.0, 1.0]})
               ) == ["body", "pickup"]
    shelf = [float((W.obstacles[0][0] + W.obstacles[0][2]) / 2),
             float((W.obstacles[0][1] + W.obstacles[0][3]) / 2)]
    r = client.post("/v1/orders", json=ok | {"dropoff": shelf})
    assert loc(r) == ["body", "dropoff"] and "free" in r.json()["detail"][0]["msg"]
    assert loc(client.post("/v1/orders", json=ok | {"priority": "high"})
               )[-1] == "priority"
    assert loc(client.post("/v1/orders", json=ok | {"id": "../../etc/passwd"})
               ) == ["body", "id"]
    assert loc(client.post("/v1/orders", json=ok | {"colour": "red"}))[-1] == "colour"
    assert loc(client.put("/v1/agents/a1", json={"position": PICK, "status": "flying"})
               ) == ["body", "status"]
    assert loc(client.put("/v1/agents/a1", json={"position": [1e3, 0], "status": "idle"})
               ) == ["body", "position"]
    assert loc(client.put("/v1/agents/a%20b", json={"position": PICK, "status": "idle"})
               ) == ["path", "agent_id"]
    agv = uid("agv")
    client.put(f"/v1/agents/{agv}", json={"position": DROP, "status": "charging"})
    assert loc(client.post(f"/v1/agents/{agv}/events", json={"type": "picked_up"})
               ) == ["body", "order"]
    assert loc(client.post(f"/v1/agents/{agv}/events", json={"type": "exploded"})
               ) == ["body", "type"]
    r = client.post("/v1/orders", content=b"{not json", headers={"content-type":
                                                                 "application/json"})
    assert r.status_code == 422


def test_404_and_409(client: httpx.Client) -> None:
    assert client.get("/v1/orders/no-such-order").status_code == 404
    assert client.delete("/v1/orders/no-such-order").status_code == 404
    r = client.post("/v1/agents/no-such-agv/events", json={"type": "fault"})
    assert r.status_code == 404
    agv, oid = uid("agv"), uid("c")
    client.put(f"/v1/agents/{agv}", json={"position": DROP, "status": "charging"})
    assert client.post(f"/v1/agents/{agv}/events", json={"type": "picked_up",
                                                         "order": "nope"}).status_code == 404
    client.post("/v1/orders", json={"id": oid, "pickup": PICK, "dropoff": DROP})
    # Delivered before it was picked up; repaired while not broken; picked up while charging.
    assert client.post(f"/v1/agents/{agv}/events", json={"type": "delivered",
                                                         "order": oid}).status_code == 409
    assert client.post(f"/v1/agents/{agv}/events", json={"type": "repaired"}
                       ).status_code == 409
    assert client.post(f"/v1/agents/{agv}/events", json={"type": "picked_up",
                                                         "order": oid}).status_code == 409
    client.delete(f"/v1/orders/{oid}")
    assert client.post(f"/v1/agents/{agv}/events", json={"type": "picked_up",
                                                         "order": oid}).status_code == 409


def test_events_stream_sends_the_floor_then_plans(service, client: httpx.Client) -> None:
    seen: list[str] = []
    with httpx.stream("GET", service.url + "/v1/events", headers=service.headers,
                      timeout=10.0) as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        oid = uid("sse")
        client.post("/v1/orders", json={"id": oid, "pickup": PICK, "dropoff": DROP})
        for line in r.iter_lines():
            if line.startswith("event: "):
                seen.append(line[7:])
            if seen.count("plan") >= 2:
                break
    client.delete(f"/v1/orders/{oid}")
    assert seen[0] == "floor" and seen[1] == "plan"


def test_dashboard_page_is_static_and_self_contained(service) -> None:
    r = httpx.get(service.url + "/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert "connect-src 'self'" in r.headers["content-security-policy"]
    assert "http://" not in r.text and "https://" not in r.text  # no CDN, nothing external
    assert "<canvas" in r.text


def test_a_busy_agv_on_its_way_can_be_given_a_better_order(client: httpx.Client) -> None:
    """An AGV that reports busy on its way to a pickup is still planned (and re-planned)."""
    a = uid("agv")
    far, near = W.pickups[47].tolist(), W.pickups[0].tolist()
    client.put(f"/v1/agents/{a}", json={"position": DROP, "status": "idle"})
    o1 = uid("far")
    client.post("/v1/orders", json={"id": o1, "pickup": far, "dropoff": DROP})
    wait_for(lambda: client.get(f"/v1/orders/{o1}").json()["agent"] == a)
    client.put(f"/v1/agents/{a}", json={"position": DROP, "status": "busy"})
    # A second free AGV near the far pickup: the plan swaps, and the busy one gets the
    # near order instead of nothing.
    b = uid("agv")
    client.put(f"/v1/agents/{b}", json={"position": far, "status": "idle"})
    o2 = uid("near")
    client.post("/v1/orders", json={"id": o2, "pickup": near, "dropoff": DROP})
    wait_for(lambda: client.get(f"/v1/orders/{o1}").json()["agent"] == b
             and client.get(f"/v1/orders/{o2}").json()["agent"] == a)
    for o in (o1, o2):
        client.delete(f"/v1/orders/{o}")
    for x in (a, b):
        client.put(f"/v1/agents/{x}", json={"position": DROP, "status": "charging"})
