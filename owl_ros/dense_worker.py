"""The dense stage in a child process of its own (parameter ``dense_process``, default true).

Why a process: the node's sparse engine and the dense stage are both numpy and OpenCV
driven from Python, and in one process they take turns at Python's GIL. On two cores the
dense thread then slows the sparse engine by more than its CPU share (docs/dense.md,
"Dense in a process of its own"). A child process has an interpreter of its own; what
crosses between the two is small (the two working images and a few matrices one way, the
published arrays the other, about 1 MB a frame at 320x240, a millisecond of copying).

The child is started with ``python -P -m owl_ros.dense_worker FD`` and talks to the node over
a socket pair (:class:`multiprocessing.connection.Connection`, pickled objects); it imports
only numpy, OpenCV and ``owl_core``, names itself ``owl-dense`` (``top``, ``ps``), runs
numpy's BLAS on one thread like the node, and exits when the node closes its end (or dies:
the socket's other end is then closed by the kernel).

What is here has no ROS import, so the child stays light: :func:`message_arrays` turns a
:class:`~owl_core.dense.DenseResult` into the arrays the dense topics publish, and
:class:`DenseSummary` is what ``owl: dense`` reports of one result; ``owl_ros.dense_outputs``
wraps both into messages in either mode.
"""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from owl_core.camera import CameraModel
from owl_core.dense import DenseOptions, DenseOwl, DenseResult, ImagePair, Readout
from owl_core.errors import OwlError

__all__ = [
    "CLOUD_DTYPE",
    "DenseInputs",
    "DenseProcess",
    "DenseProcessError",
    "DenseRequest",
    "DenseSummary",
    "message_arrays",
    "summarize",
]

#: owl/dense_points' fields, in order.
CLOUD_DTYPE = np.dtype(
    [
        ("x", np.float32),
        ("y", np.float32),
        ("z", np.float32),
        ("u", np.float32),
        ("v", np.float32),
        ("L", np.float32),
        ("range_over_speed", np.float32),
        ("confidence", np.float32),
    ]
)


@dataclass(frozen=True)
class DenseSummary:
    """What ``owl: dense`` reports of one dense result.

    Attributes:
        stamp_ns: the frame's stamp, ns.
        confident_fraction: confident over textured pixels, 0..1 (NaN: nothing textured).
        total_s: the dense stage's wall time for the frame, s.
        ttc_s: the shortest time to contact in the path cone, s (NaN: none, or no heading).
        ttc_pixel: (u, v) of that pixel in the input image, or None.
        ttc_cone_pixels: working pixels inside the path cone, count.
        reasons: why pixels or the whole frame are missing (empty when none).
    """

    stamp_ns: int
    confident_fraction: float
    total_s: float
    ttc_s: float
    ttc_pixel: tuple[float, float] | None
    ttc_cone_pixels: int
    reasons: tuple[str, ...]


def summarize(result: DenseResult) -> DenseSummary:
    """The :class:`DenseSummary` of one result."""
    ttc = result.ttc
    pixel = None
    if ttc is not None and ttc.pixel is not None:
        pixel = (float(ttc.pixel[0]), float(ttc.pixel[1]))
    return DenseSummary(
        stamp_ns=int(result.stamp_ns),
        confident_fraction=result.confident_fraction,
        total_s=float(result.timings.get("total", math.nan)),
        ttc_s=float(ttc.seconds) if ttc is not None else math.nan,
        ttc_pixel=pixel,
        ttc_cone_pixels=int(ttc.pixels_in_cone) if ttc is not None else 0,
        reasons=tuple(result.reasons),
    )


def message_arrays(
    result: DenseResult, speed: float | None, stride: int, wanted: Callable[[str], bool]
) -> dict[str, Any]:
    """The arrays behind the dense topics where ``wanted(topic)`` is true.

    ``owl/looming``, ``owl/range_over_speed``, ``owl/depth/image``: (h, w) float32 C-order
    images (1/s, s, s or m), NaN where not confident; ``owl/dense_points``: (n,)
    :data:`CLOUD_DTYPE` records of the confident pixels every ``stride`` working px;
    ``owl/time_to_contact``: (3,) float64 bearing times the time to contact (s), NaN when
    there is none. ``speed`` (m/s) makes the depth image and the cloud metric; None keeps
    seconds. ``owl/depth/camera_info`` needs no array.
    """
    out: dict[str, Any] = {}
    conf = result.confident
    nan = np.float32(np.nan)
    scale = np.float32(speed) if speed is not None else np.float32(1.0)

    def image(a: Any) -> Any:
        return np.ascontiguousarray(np.where(conf, a, nan), dtype=np.float32)

    if wanted("owl/looming"):
        out["owl/looming"] = image(result.looming)
    if wanted("owl/range_over_speed"):
        out["owl/range_over_speed"] = image(result.range_over_speed)
    if wanted("owl/depth/image"):
        out["owl/depth/image"] = image(result.depth_over_speed * scale)
    if wanted("owl/dense_points"):
        sub = (slice(None, None, stride), slice(None, None, stride))
        keep = conf[sub]
        pts = result.points[sub][keep] * scale
        v, u = np.nonzero(keep)
        cloud = np.zeros(pts.shape[0], dtype=CLOUD_DTYPE)
        cloud["x"], cloud["y"], cloud["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        cloud["u"] = (u * stride).astype(np.float32)
        cloud["v"] = (v * stride).astype(np.float32)
        cloud["L"] = result.looming[sub][keep]
        cloud["range_over_speed"] = result.range_over_speed[sub][keep]
        cloud["confidence"] = result.confidence[sub][keep]
        out["owl/dense_points"] = cloud
    if wanted("owl/time_to_contact"):
        ttc = result.ttc
        point = np.full(3, np.nan)
        if ttc is not None and ttc.bearing is not None and math.isfinite(ttc.seconds):
            point = np.asarray(ttc.bearing, dtype=np.float64) * ttc.seconds
        out["owl/time_to_contact"] = point
    return out


@dataclass(frozen=True)
class DenseInputs:
    """What the dense stage measures one frame from, read from the engine at hand-over.

    Attributes:
        pair: the image pair (working images, stamps).
        rotation: (3, 3) gyro rotation from the pair's first to its second stamp (bias
            removed), or None without gyro coverage.
        heading: (3,) the sparse engine's heading at the second stamp, or None.
        heading_sigma_rad: its 1-sigma, rad.
        speed_rate: the engine's ``d ln|t|/dt`` at the second stamp, 1/s.
        readout: with a rolling shutter the gyro rotations of both images' row times
            (:class:`~owl_core.dense.Readout`), or None.
    """

    pair: ImagePair
    rotation: Any
    heading: Any
    heading_sigma_rad: float
    speed_rate: float
    readout: Readout | None = None

    def measure(self, dense: DenseOwl) -> DenseResult:
        """Dense OWL of these inputs with ``dense`` (:meth:`DenseOwl.measure`).

        Raises:
            OwlError: malformed rotation or heading.
        """
        return dense.measure(
            self.pair,
            self.rotation,
            self.heading,
            self.heading_sigma_rad,
            self.speed_rate,
            self.readout,
        )


@dataclass(frozen=True)
class DenseRequest:
    """One frame's dense work as it crosses to the child process.

    Attributes:
        camera: the input images' camera model.
        options: the dense stage's settings (a change rebuilds the child's stage).
        inputs: what the frame is measured from.
        speed: m/s for metric depth and cloud, or None (seconds).
        stride: owl/dense_points stride, working px.
        topics: the topics to build arrays for.
    """

    camera: CameraModel
    options: DenseOptions
    inputs: DenseInputs
    speed: float | None
    stride: int
    topics: frozenset[str]


class _Measurer:
    """The child's side: one :class:`DenseOwl` per camera and options, reused."""

    def __init__(self) -> None:
        self._dense: DenseOwl | None = None

    def __call__(self, req: DenseRequest) -> tuple[str, Any, Any]:
        """``("ok", summary, arrays)`` or ``("error", one line, None)``."""
        try:
            dense = self._dense
            if dense is None or dense.camera != req.camera or dense.options != req.options:
                dense = self._dense = DenseOwl(req.camera, req.options)
            result = req.inputs.measure(dense)
            arrays = message_arrays(result, req.speed, req.stride, req.topics.__contains__)
        except OwlError as err:
            return ("error", f"dense: {err}", None)
        except Exception as err:  # a process boundary: say it in the node's status, go on
            return ("error", f"dense process: {type(err).__name__}: {err}", None)
        return ("ok", summarize(result), arrays)


def serve(conn: Connection) -> None:
    """The child's loop: answer each :class:`DenseRequest` until the node closes its end."""
    measure = _Measurer()
    while True:
        try:
            req = conn.recv()
        except (EOFError, OSError):
            return
        if req is None:
            return
        try:
            conn.send(measure(req))
        except (BrokenPipeError, OSError):
            return


class DenseProcessError(RuntimeError):
    """The dense child process could not be started or stopped answering."""


class DenseProcess:
    """The node's handle on the dense child process, started on the first request.

    :meth:`measure` (or :meth:`send`, then :meth:`receive`: ``owl_process`` lets the child
    measure one frame while its engine runs the next) blocks without the GIL until the
    child answers; one request at a time. A child that died is started again at the next
    request.

    Args:
        python: the interpreter to run the child with (default this one).
        start_timeout_s: longest wait for the child's first answer, s (imports).
        timeout_s: longest wait for any later answer, s.
    """

    def __init__(
        self, python: str | None = None, start_timeout_s: float = 60.0, timeout_s: float = 30.0
    ) -> None:
        self._python = python or sys.executable
        self._start_timeout_s = start_timeout_s
        self._timeout_s = timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._answered = False
        self._waiting = False
        self._lock = threading.Lock()
        self.starts = 0

    @property
    def pid(self) -> int | None:
        """The child's process id while it runs, else None."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def _start(self) -> Connection:
        ours, theirs = socket.socketpair()
        fd = theirs.fileno()
        env = dict(os.environ)  # the child finds owl_ros where this process found it
        path: Sequence[str] = [p for p in sys.path if p]
        env["PYTHONPATH"] = os.pathsep.join(path)
        try:
            self._proc = subprocess.Popen(
                # -P: not the working directory first on sys.path (3.11+), so the child
                # imports the owl_ros this process runs, not a checkout it stands in
                [self._python, "-P", "-m", "owl_ros.dense_worker", str(fd)],
                pass_fds=(fd,),
                env=env,
                stdin=subprocess.DEVNULL,
            )
        except OSError as err:
            ours.close()
            raise DenseProcessError(f"could not start the dense process: {err}") from err
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._answered = False
        self.starts += 1
        return self._conn

    def measure(self, req: DenseRequest) -> tuple[str, Any, Any]:
        """The child's answer to one request (``("ok", DenseSummary, arrays)`` or
        ``("error", line, None)``): :meth:`send` then :meth:`receive`.

        Raises:
            DenseProcessError: the child could not be started, died, or did not answer in
                time (it is then stopped; the next call starts a new one).
        """
        self.send(req)
        return self.receive()

    def send(self, req: DenseRequest) -> None:
        """Hand one request to the child (starting it if none runs) and return at once;
        :meth:`receive` gets the answer. One request at a time.

        Raises:
            DenseProcessError: as :meth:`measure`.
        """
        with self._lock:
            conn = self._conn if self._conn is not None else self._start()
            try:
                conn.send(req)
            except OSError as err:
                code = self._stop_locked()
                raise DenseProcessError(f"the dense process exited (code {code})") from err
            self._waiting = True

    def receive(self) -> tuple[str, Any, Any]:
        """The answer to the request :meth:`send` handed over (blocks, without the GIL).

        Raises:
            DenseProcessError: as :meth:`measure`, or no request is waiting.
        """
        with self._lock:
            conn = self._conn
            if conn is None or not self._waiting:
                raise DenseProcessError("no request is waiting for the dense process")
            self._waiting = False
            wait = self._timeout_s if self._answered else self._start_timeout_s
            try:
                if not conn.poll(wait):
                    self._stop_locked()
                    raise DenseProcessError(f"the dense process gave no answer in {wait:g} s")
                answer: tuple[str, Any, Any] = conn.recv()
            except (EOFError, OSError) as err:
                code = self._stop_locked()
                raise DenseProcessError(f"the dense process exited (code {code})") from err
            self._answered = True
            return answer

    @property
    def waiting(self) -> bool:
        """Whether a request was sent and its answer not yet received."""
        return self._waiting

    def _stop_locked(self, timeout_s: float = 5.0) -> int | None:
        self._waiting = False
        conn, self._conn = self._conn, None
        proc, self._proc = self._proc, None
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
            conn.close()
        if proc is None:
            return None
        try:
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()

    def close(self, timeout_s: float = 5.0) -> int | None:
        """Stop the child (it finishes the request at hand first); its exit code, or None
        when none ran."""
        with self._lock:
            return self._stop_locked(timeout_s)


def _main(argv: Sequence[str]) -> int:
    from owl_core.os_thread import name_os_thread
    from owl_ros.threads import one_blas_thread

    name_os_thread("owl-dense")
    one_blas_thread()
    if len(argv) != 1 or not argv[0].isdigit():
        print(
            f"owl_ros.dense_worker: expected one file descriptor, got {list(argv)}",
            file=sys.stderr,
        )
        return 2
    serve(Connection(int(argv[0])))
    return 0


if __name__ == "__main__":
    # the classes that cross the socket are pickled by module name: run them from
    # owl_ros.dense_worker, not from this copy of the module named __main__
    from owl_ros import dense_worker

    sys.exit(dense_worker._main(sys.argv[1:]))
