"""bags.dds: the Fast DDS profile for large images, its environment rule, and that Fast DDS
really takes it (the publisher's shared-memory segment grows to the profile's size)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from bags import dds

ROOT = Path(__file__).resolve().parents[2]


def test_installed_config_file_is_the_profile() -> None:
    assert (ROOT / "config" / "fastdds_large_images.xml").read_text() == dds.PROFILE_XML
    root = ET.fromstring(dds.PROFILE_XML)
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    size = root.find("f:transport_descriptors/f:transport_descriptor/f:segment_size", ns)
    assert size is not None and int(size.text or 0) == dds.SEGMENT_BYTES


def test_profile_is_chosen_only_when_the_user_chose_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    env: dict[str, str] = {}
    path = dds.prefer_large_image_profile(env)
    assert path == tmp_path / "owl_ros" / "fastdds_large_images.xml"
    assert env == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(path)}
    assert path.read_text() == dds.PROFILE_XML
    assert dds.prefer_large_image_profile({"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"})
    for user in (
        {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"},
        {"FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"},
        {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
    ):
        env = dict(user)
        assert dds.prefer_large_image_profile(env) is None
        assert env == user  # untouched


_PUBLISHER = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from bags.dds import prefer_large_image_profile
    if sys.argv[1] == "profile":
        prefer_large_image_profile()
    import rclpy
    from rclpy.context import Context
    from sensor_msgs.msg import Image
    shm = Path("/dev/shm")
    before = {p.name for p in shm.iterdir()}
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(sys.argv[2]))
    node = rclpy.create_node("owl_dds_probe", context=ctx)
    pub = node.create_publisher(Image, "/owl_dds_probe", 1)
    msg = Image(height=720, width=1280, encoding="mono8", step=1280)
    msg.data = bytes(1280 * 720)
    pub.publish(msg)
    time.sleep(0.5)
    new = [p for p in shm.iterdir() if p.name not in before and p.name.startswith("fast")]
    print(max((p.stat().st_size for p in new), default=0))
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)
    """
)


@pytest.mark.skipif(not Path("/dev/shm").is_dir(), reason="no /dev/shm")
def test_fast_dds_takes_the_profile(tmp_path: Path) -> None:
    # The largest shared-memory segment the publisher's participant created: the
    # profile's 16 MiB with it, Fast DDS's default (512 KiB plus its bookkeeping) without.
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS")
    }
    env["XDG_CACHE_HOME"] = str(tmp_path)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if env["RMW_IMPLEMENTATION"] != "rmw_fastrtps_cpp":
        pytest.skip("not Fast DDS")
    sizes = {}
    for mode in ("profile", "default"):
        out = subprocess.run(
            [sys.executable, "-c", _PUBLISHER, mode, str(180 + os.getpid() % 50)],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
            cwd=ROOT,
        )
        sizes[mode] = int(out.stdout.strip().splitlines()[-1])
    assert sizes["profile"] >= dds.SEGMENT_BYTES, sizes
    assert 0 < sizes["default"] < 2 * 1024 * 1024, sizes
