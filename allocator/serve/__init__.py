"""``agv serve``: the fleet dispatch service (optional extra ``[serve]``: FastAPI, uvicorn).

Warehouse software in any language reports AGV states and events and posts transport orders
over HTTP; the service keeps them in SQLite, runs one of the library's lifelong dispatchers
(:mod:`allocator.dispatch`) on the floor's obstacle-aware distances
(:class:`allocator.distances.FloorDistances`), and publishes the plan (``GET /v1/plan``, and
as server-sent events on ``GET /v1/events``). See ``docs/service.md``.

- :mod:`allocator.serve.store`: the SQLite store (WAL mode, one transaction per change);
- :mod:`allocator.serve.fleet`: the state, its rules, the plan;
- :mod:`allocator.serve.app`: the HTTP API;
- :mod:`allocator.serve.simulate`: the simulator standing in for the fleet (``--simulate``).

This module imports nothing heavy: ``agv --help`` does not load FastAPI.
"""

from __future__ import annotations

from allocator.serve.cli import add_serve_parser, run_serve

__all__ = ["add_serve_parser", "run_serve"]
