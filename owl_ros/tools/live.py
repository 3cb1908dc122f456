"""owl_node in its own process: start it, wait until it is discovered, stop it cleanly.

The one way the tools (latency, soak, demo) and the DDS tests run the live node::

    node = LiveNode(["-r", "image:=/cam/image", "-p", "max_features:=500"], env=env).start()
    try:
        node.wait_until(lambda: ros_node.count_publishers("/owl/points") > 0)
        ...  # publish, measure
    finally:
        code, err = node.stop()  # SIGINT, then the exit status and what it wrote on stderr

``env`` carries the private ``ROS_DOMAIN_ID`` (and ``RMW_IMPLEMENTATION``); ``ros_args``
are what follows ``--ros-args`` on the command line. The node is started as
``python -m owl_ros.node`` with the running interpreter unless ``command`` names another
executable (the packaging test runs the installed ``lib/owl_ros/owl_node``).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import IO, Any

from owl_ros.tools.errors import LiveNodeError

#: How often :meth:`LiveNode.wait_until` checks its condition, s.
POLL_S = 0.05


class LiveNode:
    """One ``owl_node`` process.

    Args:
        ros_args: arguments after ``--ros-args`` (``-r FROM:=TO``, ``-p NAME:=VALUE``,
            ``--params-file PATH``).
        env: the process environment (the DDS domain is chosen there).
        command: the executable and its leading arguments; default
            ``[sys.executable, "-m", "owl_ros.node"]``.
        stdout, stderr: where the node's output goes: ``subprocess.PIPE`` (kept, returned by
            :meth:`stop`), ``subprocess.DEVNULL``, ``subprocess.STDOUT`` or an open file.
    """

    def __init__(
        self,
        ros_args: Sequence[str] = (),
        *,
        env: Mapping[str, str],
        command: Sequence[str] | None = None,
        stdout: int | IO[Any] | None = subprocess.DEVNULL,
        stderr: int | IO[Any] | None = subprocess.PIPE,
    ) -> None:
        head = list(command) if command is not None else [sys.executable, "-m", "owl_ros.node"]
        self.argv = [*head, "--ros-args", *ros_args] if ros_args else head
        self.env = dict(env)
        self._stdout = stdout
        self._stderr = stderr
        self._proc: subprocess.Popen[str] | None = None
        #: True when :meth:`stop` had to kill the node (it ignored SIGINT).
        self.killed = False

    @property
    def proc(self) -> subprocess.Popen[str]:
        """The running process (LiveNodeError before :meth:`start`)."""
        if self._proc is None:
            raise LiveNodeError("owl_node was not started")
        return self._proc

    @property
    def pid(self) -> int:
        """The node's process id."""
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        """The exit status once the node has exited, else None."""
        return self.proc.poll()

    def start(self) -> LiveNode:
        """Start the node; returns self."""
        self._proc = subprocess.Popen(
            self.argv, env=self.env, stdout=self._stdout, stderr=self._stderr, text=True
        )
        return self

    def running(self) -> bool:
        """True while the node process is alive."""
        return self._proc is not None and self._proc.poll() is None

    def wait_until(
        self, ready: Callable[[], bool], timeout_s: float = 30.0, what: str = "discovered"
    ) -> None:
        """Poll ``ready()`` (e.g. the node's publishers discovered) until it is true.

        Raises:
            LiveNodeError: the node exited first (with its exit status), or ``timeout_s``
                passed (``what`` says what was awaited).
        """
        deadline = time.monotonic() + timeout_s
        while not ready():
            code = self.proc.poll()
            if code is not None:
                raise LiveNodeError(f"owl_node exited with code {code} before it was {what}")
            if time.monotonic() > deadline:
                raise LiveNodeError(f"owl_node was not {what} within {timeout_s:g} s")
            time.sleep(POLL_S)

    def stop(self, timeout_s: float = 15.0) -> tuple[int, str]:
        """SIGINT the node (when still running) and wait for it; kill it after ``timeout_s``.

        Returns:
            (exit status, what it wrote on stderr when that was piped, or on stdout when
            ``stderr=subprocess.STDOUT``; else ""). :attr:`killed` says whether it had to be
            killed.
        """
        proc = self.proc
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.killed = True
            proc.kill()
            out, err = proc.communicate()
        text = out if self._stderr == subprocess.STDOUT else err
        return int(proc.returncode), text or ""

    def __enter__(self) -> LiveNode:
        return self.start() if self._proc is None else self

    def __exit__(self, *exc: object) -> None:
        if self._proc is not None:
            self.stop()
