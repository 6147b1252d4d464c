"""Run ``agv serve`` as a child process on a free local port (tests, benchmarks, demos)."""

from __future__ import annotations

import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["ServiceProcess", "free_port", "write_key_file"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_key_file(path: str | Path) -> str:
    """Write a fresh random API key to ``path`` with mode 0600; return it."""
    key = secrets.token_urlsafe(32)
    p = Path(path)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    os.chmod(p, 0o600)
    return key


class ServiceProcess:
    """``agv serve`` in a child process.

    Parameters
    ----------
    folder : Path
        Where the database, the key file and the log go.
    args : list of str
        Extra ``agv serve`` arguments (``--floor``, ``--simulate``, ``--method``...).
    db : str, optional
        Database file name in ``folder`` (default ``service.db``).
    """

    def __init__(self, folder: str | Path, args: list[str], db: str = "service.db") -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.args = list(args)
        self.db = self.folder / db
        self.key_file = self.folder / "api.key"
        self.key = write_key_file(self.key_file) if not self.key_file.exists() else \
            self.key_file.read_text().strip()
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        self.log_path = self.folder / "service.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.key}"}

    def command(self) -> list[str]:
        return [sys.executable, "-m", "allocator.cli", "serve", "--port", str(self.port),
                "--db", str(self.db), "--api-key-file", str(self.key_file), *self.args]

    def start(self, timeout: float = 120.0) -> ServiceProcess:
        """Start and wait until ``/healthz`` answers."""
        import httpx

        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        log = open(self.log_path, "ab")  # noqa: SIM115 - the child keeps it
        self.proc = subprocess.Popen(self.command(), stdout=log, stderr=subprocess.STDOUT,
                                     env=env, cwd=self.folder)
        log.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"agv serve exited with {self.proc.returncode}:\n"
                                   f"{self.log()}")
            try:
                if httpx.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        self.kill()
        raise RuntimeError(f"agv serve did not answer within {timeout} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def kill(self) -> None:
        """``kill -9``: no shutdown handlers run."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        """A graceful stop (SIGTERM), then SIGKILL after 10 s."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()
