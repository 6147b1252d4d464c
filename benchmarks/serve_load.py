"""Load and chaos test of ``agv serve``: 200 AGVs reporting at 1 Hz, 20 orders per second.

    python benchmarks/serve_load.py [--agents 200] [--orders-per-s 20] [--duration 60]
        [--plan-hz 5] [--floor warehouse-200] [--method hungarian] [--chaos] [--seed 0]
        [--out benchmarks/results/serve]

A real ``agv serve`` runs in a child process on 127.0.0.1 (its own SQLite database, a fresh
key); this process plays the warehouse software and the fleet, with one asyncio loop and
httpx connection pools:

- every AGV reports its state (``PUT /v1/agents/{id}``) once a second, the reports spread
  evenly over the second; it moves at ``--speed`` along the path of its order in the plan,
  reports ``picked_up`` at the pickup and ``delivered`` at the drop-off;
- the fleet reads the plan (``GET /v1/plan``) ``--plan-hz`` times a second;
- orders arrive at ``--orders-per-s`` (evenly spaced, each with a fresh id; pickups among the
  floor's pickup points, drop-offs among its stations, drawn from a seeded generator), and
  an order whose post fails (a connection error, a 5xx) is posted again with the same id
  until it is acknowledged (at-least-once delivery made exactly-once by the ids).

``--chaos`` kills the service with SIGKILL a third of the way in, restarts it at once on the
same database and port, and carries on. At the end every order is read back from the
database and through the API: no acknowledged order may be missing or stored twice, and
every acknowledged order must be reported by ``GET /v1/orders/{id}``.

Writes ``load.json`` (or ``chaos.json``) and a Markdown summary beside it with the command,
the configuration, the machine and the date: p50 / p99 latency per request kind, errors
(5xx, unexpected 4xx, failed requests outside the chaos window), lost and duplicated orders.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import platform
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from provenance import recorded_command

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=200)
    p.add_argument("--orders-per-s", type=float, default=20.0)
    p.add_argument("--duration", type=float, default=60.0, help="seconds of load")
    p.add_argument("--plan-hz", type=float, default=5.0, help="plan reads per second")
    p.add_argument("--speed", type=float, default=1.5, help="AGV speed, world units / s")
    p.add_argument("--floor", default="warehouse-200")
    p.add_argument("--method", default="hungarian")
    p.add_argument("--chaos", action="store_true", help="kill -9 and restart mid-run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "serve")
    p.add_argument("--name", default=None,
                   help="result file name (default load, or chaos with --chaos)")
    return p.parse_args(argv)


class HTTPError(Exception):
    """A failed exchange (connection refused or reset, a malformed answer)."""


class Response:
    def __init__(self, status_code: int, body: bytes, server_ms: float | None) -> None:
        self.status_code = status_code
        self.body = body
        self.server_ms = server_ms

    def json(self) -> Any:
        return json.loads(self.body)


class Connection:
    """One keep-alive HTTP/1.1 connection on asyncio streams: a lean load generator, so
    that the figures are the service's and not a client library's (httpx's pool queues
    badly with hundreds of concurrent callers on two shared cores)."""

    def __init__(self, host: str, port: int, headers: dict[str, str]) -> None:
        self.host, self.port = host, port
        self.extra = "".join(f"{k}: {v}\r\n" for k, v in headers.items())
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.lock = asyncio.Lock()

    async def _open(self) -> None:
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)

    def _close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def request(self, method: str, url: str, json_body: Any = None) -> Response:
        async with self.lock:
            body = b"" if json_body is None else json.dumps(json_body).encode()
            head = (f"{method} {url} HTTP/1.1\r\nHost: {self.host}\r\n{self.extra}"
                    f"Content-Length: {len(body)}\r\n"
                    + ("Content-Type: application/json\r\n" if body else "") + "\r\n")
            for attempt in (0, 1):  # a kept-alive connection may have been closed: redo once
                try:
                    if self.writer is None:
                        await self._open()
                    self.writer.write(head.encode() + body)
                    await self.writer.drain()
                    line = await self.reader.readline()
                    if not line:
                        raise ConnectionResetError("closed")
                    status = int(line.split()[1])
                    length = 0
                    close = False
                    server_ms = None
                    while True:
                        h = await self.reader.readline()
                        if h in (b"\r\n", b""):
                            break
                        name, _, value = h.decode().partition(":")
                        if name.lower() == "content-length":
                            length = int(value)
                        elif name.lower() == "connection" and "close" in value.lower():
                            close = True
                        elif name.lower() == "server-timing" and "dur=" in value:
                            server_ms = float(value.split("dur=")[1].split(";")[0])
                    data = await self.reader.readexactly(length) if length else b""
                    if close:
                        self._close()
                    return Response(status, data, server_ms)
                except (OSError, asyncio.IncompleteReadError, ValueError, IndexError) as err:
                    self._close()
                    if attempt or isinstance(err, ConnectionRefusedError):
                        raise HTTPError(str(err)) from None
            raise HTTPError("unreachable")  # pragma: no cover

    def close(self) -> None:
        self._close()


class Recorder:
    def __init__(self) -> None:
        self.lat: dict[str, list[float]] = {}
        self.server: dict[str, list[float]] = {}
        self.status: dict[str, dict[str, int]] = {}
        self.failures: dict[str, int] = {}
        self.failures_in_chaos: dict[str, int] = {}
        self.chaos_window: tuple[float, float] | None = None
        self.planner_again: float | None = None
        self.down = False

    def add(self, kind: str, seconds: float, status: int, server_ms: float | None) -> None:
        self.lat.setdefault(kind, []).append(seconds)
        if server_ms is not None:
            self.server.setdefault(kind, []).append(server_ms)
        d = self.status.setdefault(kind, {})
        d[str(status)] = d.get(str(status), 0) + 1

    def fail(self, kind: str) -> None:
        target = self.failures_in_chaos if self.down else self.failures
        target[kind] = target.get(kind, 0) + 1

    def summary(self) -> dict[str, Any]:
        out = {}
        for kind, v in self.lat.items():
            a = np.asarray(v) * 1e3
            srv = np.asarray(self.server.get(kind, [np.nan]))
            out[kind] = {"n": len(a), "p50_ms": round(float(np.percentile(a, 50)), 2),
                         "p99_ms": round(float(np.percentile(a, 99)), 2),
                         "max_ms": round(float(a.max()), 2),
                         "server_p50_ms": round(float(np.percentile(srv, 50)), 2),
                         "server_p99_ms": round(float(np.percentile(srv, 99)), 2),
                         "status": self.status[kind]}
        return out


async def run_load(args: argparse.Namespace, svc: Any, world: Any, rec: Recorder,
                   acked: dict[str, dict], retried: set[str]) -> dict[str, Any]:
    rng = np.random.default_rng(args.seed)
    N = args.agents
    conns = {name: Connection("127.0.0.1", svc.port, svc.headers)
             for name in [f"agent-{i}" for i in range(N)] + ["plan"]}
    order_conns = [Connection("127.0.0.1", svc.port, svc.headers) for _ in range(16)]
    ids = [f"agv-{i:03d}" for i in range(N)]
    # The fleet starts spread over the floor's stations and pickups.
    starts = np.concatenate([world.stations, world.pickups])
    pos = starts[rng.permutation(len(starts))[:N] % len(starts)].astype(np.float64).copy()
    if len(pos) < N:
        pos = starts[rng.integers(0, len(starts), N)].astype(np.float64)
    plan: dict[str, dict] = {}
    loaded: dict[str, str] = {}  # agent -> order it carries
    t0 = time.perf_counter()
    end = t0 + args.duration
    unexpected: dict[str, int] = {}

    async def call(kind: str, method: str, url: str, ok: tuple[int, ...],
                   conn: Connection, json: Any = None) -> Response | None:
        t = time.perf_counter()
        try:
            r = await asyncio.wait_for(conn.request(method, url, json), 10.0)
        except (HTTPError, asyncio.TimeoutError):
            conn.close()
            rec.fail(kind)
            return None
        rec.add(kind, time.perf_counter() - t, r.status_code, r.server_ms)
        if r.status_code >= 500:
            rec.fail(kind)
        elif r.status_code not in ok:
            unexpected[f"{kind} {r.status_code}"] = unexpected.get(
                f"{kind} {r.status_code}", 0) + 1
        return r

    async def agent_loop(i: int) -> None:
        aid = ids[i]
        conn = conns[f"agent-{i}"]
        await asyncio.sleep(i / N)  # spread the reports over the second
        status = "idle"
        while time.perf_counter() < end:
            tick = time.perf_counter()
            entry = plan.get(aid)
            if entry is not None and entry.get("order") and entry.get("goal"):
                # Move along the path (straight to the goal while it has none) by speed x 1 s.
                budget = args.speed
                path = [np.asarray(p) for p in entry["path"][1:]] if entry["path"] else \
                    [np.asarray(entry["goal"])]
                for wp in path:
                    d = float(np.linalg.norm(wp - pos[i]))
                    if d <= budget:
                        pos[i] = wp
                        budget -= d
                    else:
                        pos[i] = pos[i] + (wp - pos[i]) * (budget / d)
                        break
                goal = np.asarray(entry["goal"])
                if np.linalg.norm(goal - pos[i]) < 1e-6:
                    order = entry["order"]
                    if entry["leg"] == "pickup" and aid not in loaded:
                        r = await call("event", "POST", f"/v1/agents/{aid}/events",
                                       (200, 409), conn, json={"type": "picked_up",
                                                         "order": order})
                        if r is not None and r.status_code == 200:
                            loaded[aid] = order
                    elif entry["leg"] == "dropoff" and loaded.get(aid) == order:
                        r = await call("event", "POST", f"/v1/agents/{aid}/events",
                                       (200, 409), conn, json={"type": "delivered",
                                                         "order": order})
                        if r is not None and r.status_code == 200:
                            loaded.pop(aid, None)
                    entry["goal"] = None
                status = "busy"
            elif aid not in loaded:
                status = "idle"
            await call("put_agent", "PUT", f"/v1/agents/{aid}", (200, 201), conn,
                       json={"position": [round(float(pos[i, 0]), 4),
                                          round(float(pos[i, 1]), 4)], "status": status})
            await asyncio.sleep(max(0.0, 1.0 - (time.perf_counter() - tick)))

    async def plan_loop() -> None:
        period = 1.0 / args.plan_hz
        while time.perf_counter() < end:
            tick = time.perf_counter()
            r = await call("get_plan", "GET", "/v1/plan?orders=false", (200,), conns["plan"])
            if r is not None and r.status_code == 200:
                for a in r.json()["agents"]:
                    old = plan.get(a["id"])
                    # Keep a reached goal cleared until the plan moves on.
                    if old is not None and old.get("order") == a["order"] and \
                            old.get("leg") == a["leg"] and not old.get("goal"):
                        continue
                    plan[a["id"]] = a
            await asyncio.sleep(max(0.0, period - (time.perf_counter() - tick)))

    async def post_order(k: int, oid: str, body: dict) -> None:
        tries = 0
        while True:
            conn = order_conns[(k + tries) % len(order_conns)]
            tries += 1
            r = await call("post_order", "POST", "/v1/orders", (200, 201), conn, json=body)
            if r is not None and r.status_code in (200, 201):
                acked[oid] = body
                if tries > 1:
                    retried.add(oid)
                return
            if r is not None and r.status_code < 500:
                return  # refused for good (counted as unexpected)
            if time.perf_counter() > end + 120:
                return
            await asyncio.sleep(min(2.0, 0.1 * 2 ** min(tries, 5)))  # back off

    async def order_loop() -> None:
        period = 1.0 / args.orders_per_s
        k = 0
        tasks = []
        while True:
            due = t0 + k * period
            if due >= end:
                break
            await asyncio.sleep(max(0.0, due - time.perf_counter()))
            p = world.pickups[rng.integers(len(world.pickups))]
            d = world.stations[rng.integers(len(world.stations))]
            oid = f"load-{args.seed}-{k}"
            body = {"id": oid, "pickup": [round(float(v), 4) for v in p],
                    "dropoff": [round(float(v), 4) for v in d],
                    "priority": int(rng.integers(0, 3))}
            tasks.append(asyncio.create_task(post_order(k, oid, body)))
            k += 1
        await asyncio.gather(*tasks)
        return k

    async def chaos() -> None:
        await asyncio.sleep(args.duration / 3)
        rec.down = True
        t = time.perf_counter()
        svc.kill()
        await asyncio.to_thread(svc.start)
        rec.down = False
        rec.chaos_window = (t - t0, time.perf_counter() - t0)
        rec.planner_again = await asyncio.to_thread(wait_planner, svc) - t0

    lags: list[float] = []

    async def lag_monitor() -> None:
        """This generator's own event-loop lag: how late a 10 ms sleep wakes up (a part of
        every client-side figure)."""
        while time.perf_counter() < end:
            t = time.perf_counter()
            await asyncio.sleep(0.01)
            lags.append(time.perf_counter() - t - 0.01)

    jobs = [asyncio.create_task(agent_loop(i)) for i in range(N)]
    jobs.append(asyncio.create_task(lag_monitor()))
    jobs.append(asyncio.create_task(plan_loop()))
    order_job = asyncio.create_task(order_loop())
    if args.chaos:
        jobs.append(asyncio.create_task(chaos()))
    await asyncio.gather(*jobs)
    posted = await order_job
    for c in [*conns.values(), *order_conns]:
        c.close()
    lag = np.asarray(lags) * 1e3 if lags else np.zeros(1)
    return {"posted": posted, "unexpected": unexpected,
            "generator_lag_ms": {"p50": round(float(np.percentile(lag, 50)), 2),
                                 "p99": round(float(np.percentile(lag, 99)), 2),
                                 "max": round(float(lag.max()), 2)},
            "elapsed_s": round(time.perf_counter() - t0, 2)}


def wait_planner(svc: Any, timeout: float = 300.0) -> float:
    """Wait until the service's planning process is ready; the time it was seen ready."""
    import httpx

    deadline = time.perf_counter() + timeout
    while time.perf_counter() < deadline:
        try:
            if httpx.get(svc.url + "/healthz", timeout=2.0).json().get("planner_ready"):
                return time.perf_counter()
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(0.2)
    raise RuntimeError("the planner did not get ready")


def verify(svc: Any, acked: dict[str, dict]) -> dict[str, Any]:
    import httpx

    with sqlite3.connect(svc.db) as db:
        rows = db.execute("SELECT id, body, status FROM orders").fetchall()
    ids = [r[0] for r in rows]
    stored = set(ids)
    lost = sorted(set(acked) - stored)
    dup = len(ids) - len(stored)
    statuses: dict[str, int] = {}
    for _, _, st in rows:
        statuses[st] = statuses.get(st, 0) + 1
    api_missing = 0
    with httpx.Client(base_url=svc.url, headers=svc.headers, timeout=10.0) as c:
        for oid in acked:
            if c.get(f"/v1/orders/{oid}").status_code != 200:
                api_missing += 1
        stats = c.get("/v1/plan").json()["stats"]
        health = c.get("/healthz").json()
    return {"acknowledged": len(acked), "stored": len(stored), "lost": len(lost),
            "lost_ids": lost[:10], "duplicated": dup, "api_missing": api_missing,
            "stored_by_status": statuses, "service_stats": stats, "service_health": health}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import sim
    from allocator.serve.cli import load_world
    from allocator.serve.process import ServiceProcess

    world = load_world(args.floor)
    assert isinstance(world, sim.World)
    folder = Path(tempfile.mkdtemp(prefix="serve-load-"))
    svc = ServiceProcess(folder, ["--floor", args.floor, "--method", args.method])
    t = time.perf_counter()
    svc.start(timeout=300)
    startup = time.perf_counter() - t
    planner_ready = wait_planner(svc) - t
    rec = Recorder()
    acked: dict[str, dict] = {}
    retried: set[str] = set()
    try:
        info = asyncio.run(run_load(args, svc, world, rec, acked, retried))
        time.sleep(1.0)
        check = verify(svc, acked)
    finally:
        svc.stop()
    lat = rec.summary()
    errors = sum(rec.failures.values()) + sum(
        v for k, v in info["unexpected"].items() if not k.startswith("event 409"))
    result = {
        "command": recorded_command(__file__),
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform()},
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "startup_s": round(startup, 2),
        "planner_ready_s": round(planner_ready, 2),
        "planner_ready_again_s": rec.planner_again,
        "latency": lat,
        "failed_requests": rec.failures,
        "failed_during_chaos": rec.failures_in_chaos,
        "chaos_window_s": rec.chaos_window,
        "unexpected_status": info["unexpected"],
        "generator_loop_lag_ms": info["generator_lag_ms"],
        "errors": errors,
        "orders_posted": info["posted"],
        "orders_retried_after_failure": len(retried),
        "elapsed_s": info["elapsed_s"],
        **check,
    }
    target = 100.0
    result["p99_target_met"] = all(lat[k]["p99_ms"] <= target for k in ("get_plan",
                                                                         "post_order")
                                   if k in lat)
    args.out.mkdir(parents=True, exist_ok=True)
    name = args.name or ("chaos" if args.chaos else "load")
    (args.out / f"{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    result["machine"]["load_average_1min_at_end"] = round(load, 2)
    lines = [f"# agv serve {'chaos' if args.chaos else 'load'} test", "",
             f"`{result['command']}` ({result['date']}; {os.cpu_count()} CPUs shared by the "
             f"service, its planning process, this load generator and other work: load "
             f"average {load:.1f} at the end)", "",
             f"{args.agents} AGVs reporting at 1 Hz, {args.orders_per_s:g} orders/s, "
             f"{args.plan_hz:g} plan reads/s for {args.duration:g} s on {args.floor} "
             f"({args.method}); the service answered {startup:.1f} s after its start and "
             f"planned from {planner_ready:.1f} s (the load starts then).", "",
             "Client: from the request written to the answer read, in this (Python) load "
             "generator; server: the service's own Server-Timing (arrival at the application "
             "to the answer).", "",
             "| request | n | client p50 ms | client p99 ms | max ms | server p50 ms | "
             "server p99 ms |", "|---|---|---|---|---|---|---|"]
    for k, v in lat.items():
        lines.append(f"| {k} | {v['n']} | {v['p50_ms']} | {v['p99_ms']} | {v['max_ms']} | "
                     f"{v['server_p50_ms']} | {v['server_p99_ms']} |")
    g = info["generator_lag_ms"]
    lines += ["", f"- the load generator's own event-loop lag (in every client figure): p50 "
              f"{g['p50']} ms, p99 {g['p99']} ms, max {g['max']} ms",
              f"- the service's event-loop lag over the last minute (/healthz): "
              f"{check['service_health'].get('loop_lag_ms')}; {check['service_health']['replans']}"
              f" plans since its (re)start, {check['service_health']['plan_seconds_mean']} s "
              "each in its planning process",
              f"- errors: {errors} (failed requests outside the chaos window "
              f"{rec.failures}, unexpected statuses {info['unexpected']})",
              f"- orders posted {info['posted']}, acknowledged {check['acknowledged']}, "
              f"stored {check['stored']}: lost {check['lost']}, duplicated "
              f"{check['duplicated']}, missing through the API {check['api_missing']}",
              f"- p99 <= 100 ms for plan reads and order creation: "
              f"{result['p99_target_met']}"]
    if args.chaos:
        lines += [f"- kill -9 at {rec.chaos_window[0]:.1f} s, answering again at "
                  f"{rec.chaos_window[1]:.1f} s and planning again at "
                  f"{rec.planner_again:.1f} s; requests failed meanwhile "
                  f"{rec.failures_in_chaos}; orders acknowledged only after a retry "
                  f"{len(retried)}"]
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    ok = errors == 0 and check["lost"] == 0 and check["duplicated"] == 0 and \
        check["api_missing"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
