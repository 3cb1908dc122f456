"""A Fast DDS profile for camera images larger than the default shared-memory segment.

On one host, Fast DDS (the default ROS 2 Jazzy middleware) sends through shared memory
(SHM) only the samples that fit the writer's segment, 512 KiB by default; larger samples
fall back to UDP over loopback, whose fragments overflow the reader's socket buffer (about
208 KiB by default on Linux) as soon as the reader is busy. A 1280x720 mono8 image is
0.92 MB: with the default transports ``owl_latency --case hd30`` measured that the node
received 112 of 274 images (best effort; the rest never reached its callback), and all of
them with this profile. The segment belongs to the *publisher*: the profile is for the
camera driver's (or the bag player's) process.

:data:`PROFILE_XML` (also installed as ``config/fastdds_large_images.xml``) keeps the
default transports, SHM and UDPv4, with a 16 MiB segment (a few 720p colour images).
:func:`prefer_large_image_profile` points ``FASTRTPS_DEFAULT_PROFILES_FILE`` at it for the
current process when the user has chosen no Fast DDS configuration and no other RMW.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

__all__ = [
    "DEFAULT_SEGMENT_BYTES",
    "PROFILE_XML",
    "SEGMENT_BYTES",
    "prefer_large_image_profile",
    "profile_path",
]

#: Fast DDS's default shared-memory segment, bytes: larger samples go over UDP.
DEFAULT_SEGMENT_BYTES = 512 * 1024
#: Shared-memory segment of the profile, bytes.
SEGMENT_BYTES = 16 * 1024 * 1024

#: The profile: Fast DDS's default transports (SHM, UDPv4) with a larger SHM segment.
PROFILE_XML = f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- Fast DDS: shared memory with a {SEGMENT_BYTES // (1024 * 1024)} MiB segment
     (default 512 KiB), plus UDPv4.
     For the process that PUBLISHES large images (camera driver, bag player):
       export FASTRTPS_DEFAULT_PROFILES_FILE=<this file>
     Without it, images over 512 KiB go over UDP loopback and are lost when the
     subscriber is busy (owl_ros README, "Large images over DDS"). -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>owl_shm_large</transport_id>
      <type>SHM</type>
      <segment_size>{SEGMENT_BYTES}</segment_size>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>owl_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="owl_large_images" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>owl_shm_large</transport_id>
        <transport_id>owl_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""

#: Environment variables by which a user has already configured Fast DDS.
_USER_CHOICES = (
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "FASTDDS_DEFAULT_PROFILES_FILE",
    "FASTDDS_BUILTIN_TRANSPORTS",
    "RMW_FASTRTPS_USE_QOS_FROM_XML",
)


def profile_path() -> Path:
    """The profile as a file (written once per user under ``$XDG_CACHE_HOME/owl_ros`` or
    ``~/.cache/owl_ros``, rewritten only if its content differs)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    path = Path(base) / "owl_ros" / "fastdds_large_images.xml"
    if not path.is_file() or path.read_text() != PROFILE_XML:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(PROFILE_XML)
        tmp.replace(path)  # atomic: a concurrent reader sees the old or the new file
    return path


def prefer_large_image_profile(env: MutableMapping[str, str] | None = None) -> Path | None:
    """Point ``FASTRTPS_DEFAULT_PROFILES_FILE`` in ``env`` (default ``os.environ``) at the
    profile, unless another RMW than Fast DDS is selected or the user configured Fast DDS
    already. Call before the process creates its first ROS context.

    Returns:
        The profile's path when it was set, else None.
    """
    env = os.environ if env is None else env
    rmw = env.get("RMW_IMPLEMENTATION", "")
    if rmw not in ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return None
    if any(env.get(name) for name in _USER_CHOICES):
        return None
    path = profile_path()
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(path)
    return path
