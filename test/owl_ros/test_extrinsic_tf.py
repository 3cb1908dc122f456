"""Node ``owl`` takes the camera-IMU rotation from TF (owl_ros.extrinsic_tf) when tf2_ros
is importable; the ``camera_to_imu_rotation_xyzw`` parameter overrides it.

tf2_ros has no PyPI wheel, so the real module cannot run in this test environment. Only
for that reason the TF path is exercised with a small stand-in ``tf2_ros`` module put in
``sys.modules``: a ``Buffer`` whose ``lookup_transform`` returns a real
geometry_msgs/TransformStamped for the one expected (IMU frame, camera frame) pair and
raises otherwise, and a ``TransformListener`` that counts its ``unregister``. Everything
else is real: rclpy (its own context on a private ROS_DOMAIN_ID), the node as ``owl_node``
builds it, its worker thread and pipeline. Messages are handed to the node's subscription
callbacks directly instead of being published over DDS. What the node reports is read from
its log lines.
"""

from __future__ import annotations

import sys
import time
import types
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu

from msg_adapters.camera_info import camera_model_to_info
from msg_adapters.image import array_to_image
from msg_adapters.stamps import make_header
from owl_core.camera import CameraModel
from owl_ros.extrinsic_tf import tf_available
from owl_ros.node import OwlNode
from owl_ros.node_report import IDENTITY_BLOCKS_TF

CAMERA_FRAME = "camera_optical_frame"
IMU_FRAME = "imu_link"
#: the rotation the stand-in TF has for imu_link <- camera_optical_frame (x, y, z, w).
TF_ROTATION = (-0.5, 0.5, -0.5, 0.5)
#: a different rotation, given as the parameter.
PARAM_ROTATION = (0.0, 0.0, 0.6, 0.8)
NOT_IMPORTABLE = "tf2_ros is not importable here"
#: short diagnostics period: the node looks TF up at each one.
PERIOD = Parameter("diagnostics_period_s", value=0.1)


class FakeTf:
    """The stand-in ``tf2_ros`` module and a record of how the node used it."""

    def __init__(self) -> None:
        self.lookups: list[tuple[str, str]] = []
        self.listeners: list[tuple[Any, Any, bool]] = []
        self.unregistered = 0  # listeners closed (tf2_ros: destroys its subscriptions)
        self.ready = True  # False: TF does not have the transform yet
        fake = self

        class Buffer:
            def lookup_transform(self, target: str, source: str, when: Any) -> Any:
                fake.lookups.append((target, source))
                if not fake.ready or (target, source) != (IMU_FRAME, CAMERA_FRAME):
                    raise LookupError(f"no transform {target} <- {source}")
                tf = TransformStamped()
                tf.header.frame_id, tf.child_frame_id = IMU_FRAME, CAMERA_FRAME
                q = tf.transform.rotation
                q.x, q.y, q.z, q.w = TF_ROTATION
                return tf

        class TransformListener:
            def __init__(self, buffer: Any, node: Any, spin_thread: bool = True) -> None:
                fake.listeners.append((buffer, node, spin_thread))

            def unregister(self) -> None:
                fake.unregistered += 1

        self.module = types.ModuleType("tf2_ros")
        self.module.Buffer = Buffer  # type: ignore[attr-defined]
        self.module.TransformListener = TransformListener  # type: ignore[attr-defined]


def feed(node: OwlNode) -> None:
    """One camera_info, image and IMU sample, with their frame_ids, through the callbacks."""
    stamp = 1_000_000_000
    camera = CameraModel(
        width=64,
        height=48,
        K=np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]),
        D=np.zeros(5),
        distortion_model="plumb_bob",
    )
    node._on_camera_info(camera_model_to_info(camera, make_header(stamp, CAMERA_FRAME)))
    image = np.zeros((48, 64), dtype=np.uint8)
    node._on_image(array_to_image(image, "mono8", header=make_header(stamp, CAMERA_FRAME)))
    imu = Imu(header=make_header(stamp, IMU_FRAME))
    imu.orientation_covariance[0] = -1.0
    node._on_imu(imu)


def engine_rotation(node: OwlNode) -> tuple[float, ...] | None:
    engine = node._pipeline.engine
    return None if engine is None else tuple(engine.options.camera_to_imu_rotation_xyzw)


def wait_for(what: Callable[[], bool], why: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not what():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {why}")
        time.sleep(0.05)


def test_no_parameter_the_rotation_comes_from_tf(
    make_owl: Callable[..., OwlNode],
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    fake = FakeTf()
    monkeypatch.setitem(sys.modules, "tf2_ros", fake.module)
    node = make_owl(PERIOD)
    assert [(node_, spin) for _, node_, spin in fake.listeners] == [(node, False)]
    feed(node)
    wait_for(lambda: engine_rotation(node) == TF_ROTATION, "the TF rotation in the engine")
    assert node.options.engine.camera_to_imu_rotation_xyzw == TF_ROTATION
    assert fake.lookups[-1] == (IMU_FRAME, CAMERA_FRAME)  # parent IMU, child camera
    n_lookups = len(fake.lookups)
    # a later, unrelated parameter change keeps the rotation TF gave
    assert node.set_parameters([Parameter("max_features", value=150)])[0].successful
    wait_for(lambda: node._pipeline.engine.options.max_features == 150, "the new engine")
    assert engine_rotation(node) == TF_ROTATION
    time.sleep(0.3)  # a few diagnostics periods: TF is looked up once it answered, no more
    assert len(fake.lookups) == n_lookups
    assert fake.unregistered == 1  # and no longer listened to
    out = capfd.readouterr()
    log = out.out + out.err
    assert "from default (identity) until TF has the IMU -> camera transform" in log, log
    line = f"camera_to_imu_rotation_xyzw {list(TF_ROTATION)} from TF ({IMU_FRAME} -> "
    assert log.count(line + f"{CAMERA_FRAME})") == 1, log
    assert NOT_IMPORTABLE not in log and "not given: using the identity" not in log, log


def test_the_parameter_wins_over_tf(
    make_owl: Callable[..., OwlNode],
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    fake = FakeTf()
    monkeypatch.setitem(sys.modules, "tf2_ros", fake.module)
    node = make_owl(PERIOD, Parameter("camera_to_imu_rotation_xyzw", value=list(PARAM_ROTATION)))
    feed(node)
    wait_for(lambda: engine_rotation(node) is not None, "the engine")
    time.sleep(0.3)  # a few diagnostics periods, when TF would be looked up
    assert engine_rotation(node) == PARAM_ROTATION
    assert fake.listeners == [] and fake.lookups == []
    out = capfd.readouterr()
    log = out.out + out.err
    assert "camera_to_imu_rotation_xyzw [0, 0, 0.6, 0.8] from parameter" in log, log
    assert "from TF" not in log, log


def test_an_identity_parameter_says_that_it_keeps_tf_out(
    make_owl: Callable[..., OwlNode],
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    """The identity from a parameter (an old copy of config/owl.yaml listed it) still wins
    over TF, and the start-up line says how to get TF's rotation instead."""
    fake = FakeTf()
    monkeypatch.setitem(sys.modules, "tf2_ros", fake.module)
    node = make_owl(PERIOD, Parameter("camera_to_imu_rotation_xyzw", value=[0.0, 0.0, 0.0, 1.0]))
    feed(node)
    wait_for(lambda: engine_rotation(node) is not None, "the engine")
    time.sleep(0.3)  # a few diagnostics periods, when TF would be looked up
    assert engine_rotation(node) == (0.0, 0.0, 0.0, 1.0)
    assert fake.listeners == [] and fake.lookups == []
    out = capfd.readouterr()
    log = out.out + out.err
    line = f"[0, 0, 0, 1] from parameter ({IDENTITY_BLOCKS_TF})"
    assert line in log, log
    assert "remove it from the parameter file" in IDENTITY_BLOCKS_TF


def test_a_parameter_set_while_tf_is_awaited_wins(
    make_owl: Callable[..., OwlNode],
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    fake = FakeTf()
    fake.ready = False
    monkeypatch.setitem(sys.modules, "tf2_ros", fake.module)
    node = make_owl(PERIOD)
    feed(node)
    wait_for(lambda: len(fake.lookups) >= 2, "TF lookups")
    assert engine_rotation(node) == (0.0, 0.0, 0.0, 1.0)
    rotation = Parameter("camera_to_imu_rotation_xyzw", value=list(PARAM_ROTATION))
    assert node.set_parameters([rotation])[0].successful
    wait_for(lambda: engine_rotation(node) == PARAM_ROTATION, "the parameter's rotation")
    fake.ready = True
    n_lookups = len(fake.lookups)
    time.sleep(0.3)  # a few diagnostics periods: TF is no longer looked up
    assert len(fake.lookups) == n_lookups and engine_rotation(node) == PARAM_ROTATION
    out = capfd.readouterr()
    assert "from TF" not in out.out + out.err


def test_without_tf2_ros_the_node_says_so_once(
    make_owl: Callable[..., OwlNode],
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    # tf2_ros is not importable in this environment; None in sys.modules makes the import
    # fail the same way on a machine that has it
    monkeypatch.setitem(sys.modules, "tf2_ros", None)
    assert not tf_available()
    node = make_owl(PERIOD)
    feed(node)
    wait_for(lambda: engine_rotation(node) is not None, "the engine")
    time.sleep(0.3)  # a few diagnostics periods
    assert engine_rotation(node) == (0.0, 0.0, 0.0, 1.0)
    out = capfd.readouterr()
    log = out.out + out.err
    assert log.count(NOT_IMPORTABLE) == 1, log
    assert "from default (identity)" in log and "from TF" not in log, log
