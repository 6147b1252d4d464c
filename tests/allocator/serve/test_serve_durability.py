"""kill -9 and a restart on the same database: every accepted order is there, none twice,
and the plan is rebuilt. Plus the start-up checks (key file, lazy imports)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import threading
import time

import httpx
import pytest

import sim
from allocator.serve.process import ServiceProcess

W = sim.warehouse_floor(20)


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if ppid == pid:
                out.append(int(entry))
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_planning_process_ends_with_the_service(tmp_path) -> None:
    """Killed at once (its planning process still starting) or later: no process is left."""
    for wait in (0.0, 8.0):
        svc = ServiceProcess(tmp_path / f"w{wait:g}", ["--floor", "warehouse-20"]).start()
        time.sleep(wait)
        kids = _children(svc.proc.pid)
        assert kids, "the planning process was not started"
        svc.kill()
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and any(_alive(k) for k in kids):
            time.sleep(0.5)
        assert not any(_alive(k) for k in kids), f"left behind: {kids}"


def test_kill9_loses_no_accepted_order(tmp_path) -> None:
    svc = ServiceProcess(tmp_path, ["--floor", "warehouse-20"]).start()
    accepted: list[str] = []
    stop = threading.Event()

    def post_orders() -> None:
        with httpx.Client(base_url=svc.url, headers=svc.headers, timeout=5.0) as c:
            k = 0
            while not stop.is_set():
                oid = f"o-{k}"
                body = {"id": oid, "pickup": W.pickups[k % len(W.pickups)].tolist(),
                        "dropoff": W.stations[k % len(W.stations)].tolist()}
                try:
                    r = c.post("/v1/orders", json=body)
                except httpx.HTTPError:
                    return  # the service died mid-request: not acknowledged
                if r.status_code in (200, 201):
                    accepted.append(oid)
                k += 1

    with httpx.Client(base_url=svc.url, headers=svc.headers) as c:
        c.put("/v1/agents/a1", json={"position": W.stations[0].tolist(), "status": "idle"})
        c.put("/v1/agents/a2", json={"position": W.stations[1].tolist(), "status": "idle"})
    t = threading.Thread(target=post_orders)
    t.start()
    # Until a few dozen are in (a fixed 2 s let too few through on a loaded machine).
    deadline = time.monotonic() + 60
    while len(accepted) <= 30 and time.monotonic() < deadline and t.is_alive():
        time.sleep(0.05)
    svc.kill()  # SIGKILL while orders are being posted
    stop.set()
    t.join(10)
    assert len(accepted) > 20
    with sqlite3.connect(svc.db) as db:
        rows = db.execute("SELECT id FROM orders").fetchall()
    ids = [r[0] for r in rows]
    assert len(ids) == len(set(ids))
    assert set(accepted) <= set(ids)  # at most the one in flight is extra, never one lost
    assert len(ids) - len(accepted) <= 1
    # Restart on the same database: the orders are back, the plan is rebuilt.
    svc2 = ServiceProcess(tmp_path, ["--floor", "warehouse-20"]).start()
    try:
        with httpx.Client(base_url=svc2.url, headers=svc2.headers) as c:
            for oid in accepted:
                assert c.get(f"/v1/orders/{oid}").status_code == 200
            deadline = time.monotonic() + 60  # the plan is rebuilt in the background
            while time.monotonic() < deadline:
                plan = c.get("/v1/plan").json()
                busy = {a["id"]: a["order"] for a in plan["agents"] if a["order"]}
                if len(busy) == 2:
                    break
                time.sleep(0.1)
            assert len(busy) == 2 and plan["stats"]["accepted"] == len(ids)
            # A replay after the restart is still the same order.
            oid = accepted[0]
            k = int(oid.split("-")[1])
            r = c.post("/v1/orders", json={"id": oid,
                                           "pickup": W.pickups[k % len(W.pickups)].tolist(),
                                           "dropoff": W.stations[k % len(W.stations)].tolist()})
            assert r.status_code == 200
    finally:
        svc2.stop()


def _serve(tmp_path, key_mode: int, key: str = "k" * 32) -> subprocess.CompletedProcess:
    kf = tmp_path / "key"
    kf.write_text(key)
    os.chmod(kf, key_mode)
    return subprocess.run([sys.executable, "-m", "allocator.cli", "serve", "--floor",
                           "warehouse-20", "--db", str(tmp_path / "x.db"), "--api-key-file",
                           str(kf), "--port", "1"], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604])
def test_refuses_a_key_file_others_can_read(tmp_path, mode: int) -> None:
    r = _serve(tmp_path, mode)
    assert r.returncode == 2
    assert "chmod 600" in r.stderr and "group or others" in r.stderr
    assert not (tmp_path / "x.db").exists()


def test_refuses_a_short_key(tmp_path) -> None:
    r = _serve(tmp_path, 0o600, key="short")
    assert r.returncode == 2 and "16" in r.stderr


def test_help_does_not_import_fastapi() -> None:
    code = ("import sys, allocator.cli as c; p = c.build_parser(); "
            "assert 'fastapi' not in sys.modules and 'uvicorn' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    r = subprocess.run([sys.executable, "-m", "allocator.cli", "serve", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "--api-key-file" in r.stdout and "127.0.0.1" in r.stdout


def test_bad_floor_and_method_are_one_line_errors(tmp_path) -> None:
    kf = tmp_path / "key"
    kf.write_text("k" * 32)
    os.chmod(kf, 0o600)
    for extra, needle in ((["--floor", str(tmp_path / "nope.map")], "does not exist"),
                          (["--floor", "warehouse-20", "--method", "bicnet-ipf"],
                           "no lifelong dispatcher")):
        r = subprocess.run([sys.executable, "-m", "allocator.cli", "serve", "--db",
                            str(tmp_path / "x.db"), "--api-key-file", str(kf), *extra],
                           capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, OMP_NUM_THREADS="1"))
        assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr
