"""The HTTP API of ``agv serve`` (FastAPI): paths, schemas, authentication, limits.

Paths (DESIGN.md, "The fleet service"): ``PUT /v1/agents/{id}``, ``POST /v1/orders``,
``GET /v1/orders/{id}``, ``DELETE /v1/orders/{id}``, ``POST /v1/agents/{id}/events``,
``GET /v1/plan``, ``GET /v1/events`` (server-sent events), ``GET /healthz``,
``GET /openapi.json``, and the dashboard at ``/``.

Every request but ``/healthz`` and the dashboard's static page ``/`` (which holds no data;
its own requests carry the key) needs ``Authorization: Bearer <key>``, compared in constant
time (:func:`hmac.compare_digest`). Bodies over ``max_body`` bytes and order batches over
``max_batch`` items are refused with 413; schema errors are 422 with FastAPI's ``detail``
list, whose ``loc`` names the field.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import hmac
import json
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from importlib import resources
from typing import Annotated, Any, Literal

from fastapi import FastAPI, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from allocator.serve.fleet import Conflict, Fleet, Invalid, NotFound

__all__ = ["create_app", "ServiceConfig"]

log = logging.getLogger("agv.serve")

ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$"
Id = Annotated[str, Field(pattern=ID_PATTERN, description="1-64 characters: letters, digits, "
                          "'.', '_', ':', '-' (not first)")]
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]
Point = Annotated[list[Coord], Field(min_length=2, max_length=2,
                                     description="[x, y] in world units")]
AgentId = Annotated[str, Path(pattern=ID_PATTERN, description="the AGV's id")]
OrderId = Annotated[str, Path(pattern=ID_PATTERN, description="the order's client-chosen id")]


@dataclass
class ServiceConfig:
    """Limits and timings of one service."""

    api_key: str
    max_body: int = 256 * 1024
    max_batch: int = 500
    replan_delay: float = 0.05
    min_replan_interval: float = 0.2
    refresh_interval: float = 1.0
    sse_queue: int = 64
    heartbeat: float = 15.0


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OrderIn(_Strict):
    id: Id
    pickup: Point
    dropoff: Point
    priority: int = Field(0, ge=-1000, le=1000, description="higher first")
    deadline: float | None = Field(None, allow_inf_nan=False, ge=0, le=1e11,
                                   description="Unix time (s) the order is due")


class OrderBatch(_Strict):
    orders: list[OrderIn] = Field(description="at most max_batch orders, all or none "
                                  "accepted")


class OrderOut(BaseModel):
    id: str
    status: Literal["open", "assigned", "loaded", "delivered", "withdrawn"]
    pickup: list[float]
    dropoff: list[float]
    priority: int
    deadline: float | None
    agent: str | None
    created: float
    picked_up: float | None
    delivered: float | None
    withdrawn: float | None


class AgentIn(_Strict):
    position: Point
    status: Literal["idle", "busy", "broken", "charging"]


class AgentOut(BaseModel):
    id: str
    position: list[float]
    status: Literal["idle", "busy", "broken", "charging"]
    order: str | None
    loaded: bool
    updated: float


class EventIn(_Strict):
    type: Literal["picked_up", "delivered", "fault", "repaired"]
    order: Id | None = Field(None, description="the order, for picked_up and delivered")


class PlanAgent(BaseModel):
    id: str
    position: list[float]
    status: str
    order: str | None
    leg: Literal["pickup", "dropoff"] | None
    goal: list[float] | None = Field(description="the point the AGV drives to")
    path: list[list[float]] = Field(description="waypoints from the AGV to its goal ([] while "
                                    "not computed yet)")


class PlanOrder(BaseModel):
    id: str
    status: str
    pickup: list[float]
    dropoff: list[float]
    priority: int
    agent: str | None


class Plan(BaseModel):
    version: int
    time: float
    agents: list[PlanAgent]
    orders: list[PlanOrder] | None = None
    stats: dict[str, Any]


class Error(BaseModel):
    detail: Any


_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": Error, "description": "missing or wrong API key"},
    413: {"model": Error, "description": "body or list too large"},
    422: {"model": Error, "description": "invalid field (detail[].loc names it)"},
}


def _error(status: int, message: str, **headers: str) -> JSONResponse:
    return JSONResponse({"detail": message}, status_code=status, headers=headers or None)


class _Limits:
    """ASGI middleware: the API key on every path but /healthz and /, the body limit, and a
    ``Server-Timing: app;dur=<ms>`` header (time from the request's arrival at the
    application to its answer's first byte)."""

    def __init__(self, app: Any, key: bytes, max_body: int) -> None:
        self.app = app
        self.key = key
        self.max_body = max_body

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        outer = send

        async def send(message: dict) -> None:  # noqa: F811 - adds Server-Timing
            if message["type"] == "http.response.start":
                dur = (time.perf_counter() - start) * 1e3
                message = dict(message)
                message["headers"] = [*message.get("headers", []),
                                      (b"server-timing", f"app;dur={dur:.2f}".encode())]
            await outer(message)

        path = scope.get("path", "")
        headers = dict(scope.get("headers") or [])
        if path not in ("/healthz", "/"):
            auth = headers.get(b"authorization", b"")
            scheme, _, token = auth.partition(b" ")
            ok = scheme.lower() == b"bearer" and hmac.compare_digest(token.strip(), self.key)
            if not ok:
                resp = _error(401, "missing or wrong API key (Authorization: Bearer <key>)",
                              **{"WWW-Authenticate": "Bearer"})
                return await resp(scope, receive, send)
        length = headers.get(b"content-length")
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                return await _error(400, "bad Content-Length")(scope, receive, send)
            if n > self.max_body:
                return await _error(413, f"body of {n} bytes is over the limit of "
                                    f"{self.max_body}")(scope, receive, send)
        if length is None and scope.get("method") in ("POST", "PUT", "PATCH", "DELETE"):
            # No Content-Length (chunked): read the body here, up to the limit, then replay it.
            chunks, seen = [], 0
            while True:
                msg = await receive()
                if msg["type"] != "http.request":
                    return
                chunks.append(msg.get("body", b""))
                seen += len(chunks[-1])
                if seen > self.max_body:
                    return await _error(413, f"body is over the limit of {self.max_body} "
                                        "bytes")(scope, receive, send)
                if not msg.get("more_body", False):
                    break
            body = b"".join(chunks)
            sent = False

            async def replay() -> dict:
                nonlocal sent
                if not sent:
                    sent = True
                    return {"type": "http.request", "body": body, "more_body": False}
                return await receive()

            return await self.app(scope, replay, send)
        await self.app(scope, receive, send)


def create_app(fleet: Fleet, config: ServiceConfig, background: list[Any] | None = None,
               worker: Any = None, worker_ready: Any = None) -> FastAPI:
    """The FastAPI application of one fleet.

    Parameters
    ----------
    fleet : Fleet
    config : ServiceConfig
    background : list of callables, optional
        ``async fn(app)`` tasks started with the service and cancelled at shutdown (the
        simulator).
    worker : concurrent.futures.Executor, optional
        A planning process (:func:`allocator.serve.fleet.start_worker`); default: plan in a
        thread of this process.
    worker_ready : concurrent.futures.Future, optional
        Done when the planning process is ready; until then requests are served and stored
        but no plan is made.
    """
    dispatch = DispatchLoop(fleet, config, worker, worker_ready)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        tasks = [asyncio.create_task(dispatch.run()), asyncio.create_task(dispatch.watch_lag())]
        for fn in background or []:
            tasks.append(asyncio.create_task(fn(app)))
        dispatch.wake()
        try:
            yield
        finally:
            dispatch.closing = True
            for q in list(dispatch.subscribers):
                with contextlib.suppress(asyncio.QueueFull):
                    q.put_nowait(None)
            for t in tasks:
                t.cancel()
            for t in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await t

    app = FastAPI(title="agv serve: fleet dispatch", version="1",
                  description="Dispatch for a fleet of AGVs: report AGV states and events, "
                  "post transport orders, read the plan. Every path but /healthz needs "
                  "`Authorization: Bearer <key>`.", lifespan=lifespan,
                  docs_url=None, redoc_url=None)  # their pages load scripts from a CDN
    app.state.fleet = fleet

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            from fastapi.openapi.utils import get_openapi

            doc = get_openapi(title=app.title, version=app.version,
                              description=app.description, routes=app.routes)
            doc.setdefault("components", {})["securitySchemes"] = {
                "bearer": {"type": "http", "scheme": "bearer",
                           "description": "the key of --api-key-file"}}
            doc["security"] = [{"bearer": []}]
            doc["paths"]["/healthz"]["get"]["security"] = []
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    app.state.dispatch = dispatch
    app.add_middleware(_Limits, key=config.api_key.encode(), max_body=config.max_body)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        # POST /v1/orders takes one order or a batch: report the errors of the form sent,
        # without pydantic's union tag in the location.
        body = getattr(exc, "body", None)
        branch = "OrderBatch" if isinstance(body, dict) and "orders" in body else "OrderIn"
        tagged = [e for e in errors if len(e.get("loc", ())) > 1
                  and e["loc"][1] in ("OrderIn", "OrderBatch")]
        if tagged:
            errors = [e | {"loc": (e["loc"][0], *e["loc"][2:])} for e in tagged
                      if e["loc"][1] == branch] + [e for e in errors if e not in tagged]
        detail = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""),
                   "type": e.get("type", "")} for e in errors]
        return JSONResponse({"detail": detail}, status_code=422)

    def fail(exc: Exception) -> JSONResponse:
        if isinstance(exc, NotFound):
            return _error(404, str(exc))
        if isinstance(exc, Conflict):
            return _error(409, str(exc))
        if isinstance(exc, Invalid):
            return JSONResponse({"detail": [{"loc": list(exc.loc), "msg": exc.msg,
                                             "type": "value_error"}]}, status_code=422)
        raise exc

    @app.get("/healthz", tags=["service"])
    async def healthz() -> dict[str, Any]:
        """Liveness (no key needed)."""
        ready = dispatch.worker_ready is None or dispatch.worker_ready.done()
        return {"ok": True, "planner_ready": ready, "agents": len(fleet.agents),
                "open_orders": len(fleet.orders), "plan_version": fleet.plan_version,
                "replans": dispatch.replans,
                "plan_seconds_mean": round(dispatch.plan_seconds / max(1, dispatch.replans), 4),
                "loop_lag_ms": dispatch.lag_ms()}

    @app.put("/v1/agents/{agent_id}", tags=["agents"], response_model=AgentOut,
             responses={**_ERRORS, 201: {"model": AgentOut}})
    async def put_agent(agent_id: AgentId, body: AgentIn) -> Any:
        """Report an AGV's state (registers it on first report)."""
        try:
            out, created = fleet.put_agent(agent_id, tuple(body.position), body.status)
        except (Invalid, Conflict, NotFound) as exc:
            return fail(exc)
        dispatch.touched(structural=created or fleet.epoch != dispatch.planned_epoch)
        return JSONResponse(out, status_code=201 if created else 200)

    @app.post("/v1/agents/{agent_id}/events", tags=["agents"], response_model=AgentOut,
              responses={**_ERRORS, 404: {"model": Error}, 409: {"model": Error}})
    async def post_event(agent_id: AgentId, body: EventIn) -> Any:
        """An AGV's event: picked_up / delivered (with the order), fault, repaired."""
        try:
            out = fleet.event(agent_id, body.type, body.order)
        except (Invalid, Conflict, NotFound) as exc:
            return fail(exc)
        dispatch.touched(structural=True)
        return out

    @app.post("/v1/orders", tags=["orders"],
              responses={**_ERRORS, 200: {"description": "a replay of an existing order",
                                          "model": OrderOut},
                         201: {"description": "accepted (stored)", "model": OrderOut},
                         409: {"model": Error}},
              status_code=201)
    async def post_order(body: OrderIn | OrderBatch) -> Any:
        """Accept a transport order (or a batch ``{"orders": [...]}``, all or none). The
        same id with the same content is the same order (200); with other content, 409."""
        batch = isinstance(body, OrderBatch)
        items = body.orders if batch else [body]
        if batch and len(items) > config.max_batch:
            return _error(413, f"{len(items)} orders in one batch, more than the limit of "
                          f"{config.max_batch}")
        dicts = [it.model_dump() | ({"_batch": True} if batch else {}) for it in items]
        try:
            results = fleet.add_orders(dicts)
        except (Invalid, Conflict, NotFound) as exc:
            return fail(exc)
        if any(created for _, created in results):
            dispatch.touched(structural=True)
        if batch:
            code = 201 if any(c for _, c in results) else 200
            return JSONResponse({"orders": [o for o, _ in results]}, status_code=code)
        order, created = results[0]
        return JSONResponse(order, status_code=201 if created else 200)

    @app.get("/v1/orders/{order_id}", tags=["orders"], response_model=OrderOut,
             responses={**_ERRORS, 404: {"model": Error}})
    async def get_order(order_id: OrderId) -> Any:
        """One order, whatever its status."""
        try:
            return fleet.get_order(order_id)
        except NotFound as exc:
            return fail(exc)

    @app.delete("/v1/orders/{order_id}", tags=["orders"], response_model=OrderOut,
                responses={**_ERRORS, 404: {"model": Error},
                           409: {"model": Error, "description": "already picked up"}})
    async def delete_order(order_id: OrderId) -> Any:
        """Withdraw an order; allowed until it is picked up (then 409)."""
        try:
            out = fleet.withdraw(order_id)
        except (Conflict, NotFound) as exc:
            return fail(exc)
        dispatch.touched(structural=True)
        return out

    @app.get("/v1/plan", tags=["plan"], response_model=Plan, responses=_ERRORS)
    async def get_plan(orders: bool = Query(True, description="include the active orders "
                                            "(false: the AGVs' part only, smaller)")) -> Any:
        """The current plan: each AGV's order, leg, goal point and path waypoints; the
        active orders; throughput and wait figures."""
        return JSONResponse(fleet.plan_view(orders=orders))

    @app.get("/v1/events", tags=["plan"], responses={
        **_ERRORS, 200: {"content": {"text/event-stream": {}},
                         "description": "server-sent events: `floor` once, then `plan` at "
                         "every plan change"}})
    async def events(request: Request) -> StreamingResponse:
        """Server-sent events: the floor once, then the plan at every change."""
        queue = dispatch.subscribe()

        async def stream() -> AsyncIterator[bytes]:
            try:
                yield _sse("floor", fleet.floor_view())
                yield _sse("plan", fleet.plan_view())
                while not dispatch.closing:
                    try:
                        item = await asyncio.wait_for(queue.get(), config.heartbeat)
                    except asyncio.TimeoutError:
                        yield b": keep-alive\n\n"
                        continue
                    if item is None:
                        break
                    yield item
            finally:
                dispatch.unsubscribe(queue)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store",
                                          "X-Accel-Buffering": "no"})

    page = resources.files("allocator.serve").joinpath("static/index.html").read_bytes()

    @app.get("/", include_in_schema=False)
    async def dashboard() -> Response:
        return HTMLResponse(page, headers={
            "Content-Security-Policy": "default-src 'none'; script-src 'unsafe-inline'; "
            "style-src 'unsafe-inline'; connect-src 'self'; img-src 'self' data:",
            "Cache-Control": "no-store", "X-Content-Type-Options": "nosniff"})

    return app


def _sse(kind: str, data: dict[str, Any]) -> bytes:
    return f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


class DispatchLoop:
    """Re-plan after changes (debounced) and on a slow timer as AGVs move; push each new
    plan to the event-stream subscribers."""

    def __init__(self, fleet: Fleet, config: ServiceConfig, worker: Any = None,
                 worker_ready: Any = None) -> None:
        self.fleet = fleet
        self.config = config
        self.worker = worker
        self.worker_ready = worker_ready
        self.subscribers: set[asyncio.Queue] = set()
        self.closing = False
        self.planned_epoch = -1
        self._event: asyncio.Event | None = None
        self._structural = True
        self.replans = 0
        self.plan_seconds = 0.0
        self._last = 0.0
        self.lags: collections.deque[float] = collections.deque(maxlen=1200)

    async def watch_lag(self, every: float = 0.05) -> None:
        """The event loop's lag: how late a short sleep wakes up (last minute, /healthz)."""
        while not self.closing:
            t = time.perf_counter()
            await asyncio.sleep(every)
            self.lags.append(time.perf_counter() - t - every)

    def lag_ms(self) -> dict[str, float | None]:
        if not self.lags:
            return {"p50": None, "p99": None, "max": None}
        v = sorted(self.lags)
        pick = lambda q: round(1e3 * v[min(len(v) - 1, int(q * len(v)))], 2)  # noqa: E731
        return {"p50": pick(0.5), "p99": pick(0.99), "max": round(1e3 * v[-1], 2)}

    def subscribe(self) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=self.config.sse_queue)
        self.subscribers.add(q)
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self.subscribers.discard(q)

    def wake(self) -> None:
        if self._event is None:
            self._event = asyncio.Event()
        self._event.set()

    def touched(self, structural: bool) -> None:
        if structural:
            self._structural = True
            self.wake()

    def publish(self) -> None:
        if not self.subscribers:
            return
        msg = _sse("plan", self.fleet.plan_view())
        for q in list(self.subscribers):
            if q.full():  # a slow reader loses the oldest plan, never blocks the loop
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(msg)

    async def run(self) -> None:
        if self._event is None:
            self._event = asyncio.Event()
        fleet = self.fleet
        if self.worker_ready is not None:
            ok = await asyncio.wrap_future(self.worker_ready)
            if not ok:  # pragma: no cover
                raise RuntimeError("the planning process did not start")
        while not self.closing:
            try:
                await asyncio.wait_for(self._event.wait(), self.config.refresh_interval)
                await asyncio.sleep(self.config.replan_delay)  # gather a burst of changes
            except asyncio.TimeoutError:
                pass
            wait = self.config.min_replan_interval - (time.monotonic() - self._last)
            if wait > 0:  # under a stream of changes, plan at most every min_replan_interval
                await asyncio.sleep(wait)
            self._last = time.monotonic()
            self._event.clear()
            self._structural = False
            epoch = fleet.epoch
            snap = fleet.snapshot()
            t0 = time.perf_counter()
            try:
                if self.worker is not None:
                    from allocator.serve.fleet import plan_in_worker

                    plan, paths = await asyncio.get_running_loop().run_in_executor(
                        self.worker, plan_in_worker, snap)
                else:
                    plan, paths = await asyncio.to_thread(fleet.compute_plan, snap)
            except Exception:  # a planning bug must not stop the service; it is logged
                log.exception("planning failed")
                await asyncio.sleep(1.0)
                continue
            self.plan_seconds += time.perf_counter() - t0
            self.replans += 1
            fleet.apply_plan(snap, plan, paths)
            self.planned_epoch = epoch
            self.publish()
