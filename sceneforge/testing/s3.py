"""A real S3 API on this machine for the tests: moto's server in a subprocess.

The object-store tests and the S3 blocks of docs/store.md run against it, so they need no AWS
account and no service started beforehand (CI runs on a clean machine): :func:`local_s3`
starts ``python -m moto.server`` on a free localhost port, waits until it answers, and
stops it when the block ends. A client reaches it through the standard variables
(:attr:`LocalS3.env`: ``AWS_ENDPOINT_URL`` and test credentials), as a user's would reach
S3.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import Iterator


@dataclass(frozen=True)
class LocalS3:
    """A running moto server: its ``endpoint`` (``http://127.0.0.1:PORT``), the environment
    that points a client at it (``env``) and the server process."""

    endpoint: str
    process: subprocess.Popen

    @property
    def env(self) -> dict[str, str]:
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": "testing",
                "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}


#: variables of the caller's environment that would point a client elsewhere
FOREIGN = ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN", "AWS_CONFIG_FILE",
           "AWS_SHARED_CREDENTIALS_FILE", "AWS_REGION")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def local_s3(*, deny_all: bool = False, timeout: float = 60.0) -> Iterator[LocalS3]:
    """A moto S3 server for the block.

    deny_all : the server checks credentials (moto's ``INITIAL_NO_AUTH_ACTION_COUNT=0``)
               and knows none, so every request is refused as S3 refuses unknown keys
    """
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in FOREIGN}
    if deny_all:
        env["INITIAL_NO_AUTH_ACTION_COUNT"] = "0"
    process = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    server = LocalS3(f"http://127.0.0.1:{port}", process)
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                urllib.request.urlopen(f"{server.endpoint}/moto-api/", timeout=1).close()
                break
            except (urllib.error.URLError, OSError):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"moto's S3 server did not start on port {port}") from None
                time.sleep(0.05)
        yield server
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
