"""Client side of ``env_server.py``: simulated environments in the simulator's own venv."""

from __future__ import annotations

import pickle
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmarks._simulator import sim_env

SERVER = Path(__file__).with_name("env_server.py")


class SimEnvError(RuntimeError):
    """The simulator's environment failed (its traceback in the message)."""


class SimEnv:
    """One ``PickPlaceEnv`` of ``source`` in a subprocess of ``simenv`` (a python with mujoco).

    Args:
        simenv: the simulator venv's python.
        tools: ``shared/tools/sim``.
        source: the episode whose scene, camera and start state the environment rebuilds.
        options: ``PickPlaceEnv.from_episode`` keyword arguments (width, height, shadows, ...).
    """

    def __init__(self, simenv: Path, tools: Path, source: Path, **options: Any) -> None:
        env = {**sim_env(), "OMP_NUM_THREADS": "1"}
        self._process = subprocess.Popen([str(simenv), str(SERVER), str(tools)], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=sys.stderr, env=env)
        self.info = self.call("open", str(source), options)

    def send(self, *request: Any) -> None:
        data = pickle.dumps(request, protocol=4)
        self._process.stdin.write(struct.pack("<Q", len(data)) + data)
        self._process.stdin.flush()

    def receive(self) -> Any:
        header = self._process.stdout.read(8)
        if len(header) < 8:
            raise SimEnvError(f"the environment's process ended (exit code {self._process.wait()})")
        (size,) = struct.unpack("<Q", header)
        status, value = pickle.loads(self._process.stdout.read(size))
        if status != "ok":
            raise SimEnvError(value)
        return value

    def call(self, *request: Any) -> Any:
        self.send(*request)
        return self.receive()

    def close(self) -> None:
        if self._process.poll() is None:
            try:
                self.send("close")
                self._process.stdin.close()
                self._process.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self._process.kill()

    def __enter__(self) -> SimEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
