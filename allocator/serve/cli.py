"""The ``agv serve`` subcommand: arguments, start-up checks, and the uvicorn server."""

from __future__ import annotations

import argparse
import os
import stat
import sys
from pathlib import Path
from typing import Any

from allocator.serve.floor import load_world, make_dispatcher

__all__ = ["add_serve_parser", "run_serve", "read_api_key", "load_world", "make_dispatcher"]

_DESCRIPTION = (
    "Run the fleet dispatch service: an HTTP API (FastAPI on uvicorn) for AGV states and "
    "events, transport orders and the plan, with the orders kept in SQLite and a live "
    "dashboard at /. Needs the [serve] extra: pip install 'agv-allocation[serve]'. See "
    "docs/service.md.")


def add_serve_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``agv serve`` on an argparse subparsers object (no heavy imports)."""
    p = sub.add_parser("serve", help="run the fleet dispatch service (HTTP API, dashboard)",
                       description=_DESCRIPTION)
    p.add_argument("--floor", metavar="FILE|SCENARIO", default=None,
                   help="the floor: a .map or JSON floor plan file, or a lifelong scenario "
                        "name such as warehouse-20 (default: the --simulate scenario's)")
    p.add_argument("--method", default="hungarian",
                   help="dispatcher: an allocator with a lifelong dispatcher (hungarian, "
                        "fifo, greedy, ...; default hungarian)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1, this machine only)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument("--db", metavar="PATH", default="agv-serve.db",
                   help="SQLite database (created if absent; default agv-serve.db)")
    p.add_argument("--api-key-file", metavar="FILE", required=True,
                   help="file holding the API key (one line, at least 16 characters); it "
                        "must not be readable by group or others (chmod 600)")
    p.add_argument("--simulate", metavar="SCENARIO", default=None,
                   help="let the simulator stand in for the fleet (e.g. warehouse-20): its "
                        "AGVs report their states and follow the plan")
    p.add_argument("--sim-rate", type=float, default=10.0, metavar="HZ",
                   help="simulator steps per second (default 10: real time at dt 0.1)")
    p.add_argument("--sim-faults", default=None, metavar="RATE:REPAIR",
                   help="simulated breakdowns: rate per AGV-step and repair steps, e.g. "
                        "0.0005:60")
    p.add_argument("--sim-seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--sync", choices=("normal", "full"), default="normal",
                   help="SQLite synchronous mode: normal survives a killed process, full a "
                        "power cut too (an fsync per write); default normal")
    p.add_argument("--plan-in-thread", dest="plan_process", action="store_false",
                   help="plan in a thread of the service's process instead of a separate "
                        "planning process (saves memory; slower answers under load)")
    p.add_argument("--log-level", default="warning",
                   choices=("critical", "error", "warning", "info", "debug"),
                   help="uvicorn's log level (default warning)")
    p.set_defaults(func=run_serve)
    return p


def read_api_key(path: str | Path) -> str:
    """The API key from a file that only its owner can read.

    Raises
    ------
    ValueError
        A missing file, a file readable or writable by group or others, or a key shorter
        than 16 characters or with spaces.
    """
    p = Path(path)
    try:
        st = p.stat()
    except OSError as err:
        raise ValueError(f"cannot read the API key file {p}: {err.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"the API key file {p} is not a regular file")
    if st.st_mode & 0o077:
        raise ValueError(f"the API key file {p} is accessible by group or others (mode "
                         f"{stat.S_IMODE(st.st_mode):04o}); run: chmod 600 {p}")
    key = p.read_text(encoding="utf-8").strip()
    if len(key) < 16 or any(c.isspace() for c in key) or not key.isprintable():
        raise ValueError(f"the API key in {p} must be one word of at least 16 printable "
                         "characters")
    return key


def build_service(args: argparse.Namespace) -> tuple[Any, Any]:
    """The app and its fleet, from parsed arguments (no server started)."""
    from allocator.distances import FloorDistances
    from allocator.serve.app import ServiceConfig, create_app
    from allocator.serve.fleet import Fleet
    from allocator.serve.store import Store

    key = read_api_key(args.api_key_file)
    floor = args.floor or args.simulate
    if floor is None:
        raise ValueError("give --floor FILE|SCENARIO (or --simulate SCENARIO)")
    world = load_world(floor)
    dispatcher = make_dispatcher(args.method)
    worker = ready = None
    if args.plan_process:  # builds its own copy of the floor's distances meanwhile
        from allocator.serve.fleet import start_worker

        worker, ready = start_worker(floor, args.method)
    store = Store(args.db, sync=args.sync)
    store.start_checkpointer()
    # With a planning process, this one only checks orders' trips: no table of the fixed
    # points' distance fields (the slow part of start-up on a large floor), fields on demand.
    distances = FloorDistances(world, table_bytes=0) if worker is not None else \
        FloorDistances(world)
    fleet = Fleet(world, dispatcher, store, distances)
    background = []
    if args.simulate:
        from allocator.serve.simulate import SimulatedFleet

        sim_fleet = SimulatedFleet(fleet, args.simulate, rate=args.sim_rate,
                                   faults=args.sim_faults, seed=args.sim_seed)
        background.append(sim_fleet.run)
    # The service answers at once; plans start when the planning process is ready.
    app = create_app(fleet, ServiceConfig(api_key=key), background=background, worker=worker,
                     worker_ready=ready)
    app.state.worker = worker
    return app, fleet


def run_serve(args: argparse.Namespace) -> int:
    """Entry point of ``agv serve``."""
    try:
        import uvicorn
    except ImportError:
        raise ValueError("agv serve needs the [serve] extra: pip install "
                         "'agv-allocation[serve]'") from None
    if not 0 < args.port < 65536:
        raise ValueError(f"--port must be in 1..65535, got {args.port}")
    app, fleet = build_service(args)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    print(f"agv serve: {len(fleet.agents)} AGVs and {len(fleet.orders)} open orders from "
          f"{args.db}; listening on http://{args.host}:{args.port}", file=sys.stderr,
          flush=True)
    config = uvicorn.Config(app, host=args.host, port=args.port, log_level=args.log_level,
                            access_log=False, timeout_graceful_shutdown=2,
                            lifespan="on", server_header=False)
    import gc

    gc.collect()
    gc.freeze()  # the floor and the loaded state: out of the collector's way from now on
    try:
        uvicorn.Server(config).run()
    finally:
        if app.state.worker is not None:
            app.state.worker.shutdown(wait=False, cancel_futures=True)
        fleet.store.close()
    return 0
