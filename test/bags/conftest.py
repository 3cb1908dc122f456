"""Fixtures for bag tests: an independent reader (the `mcap` package + mcap_ros2 decoder).

Every bag written in a test is read back with rosbags (through bags.io) AND with this
reader, so a bag that only rosbags understands would fail.

Also ``limited_run``: a tool run in a child process whose files cannot grow past a size,
so that its writes fail for real (EFBIG) as on a full disk.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, DataEnd
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory


@dataclass(frozen=True)
class McapMessage:
    """One message as the `mcap` reader sees it."""

    topic: str
    schema_name: str
    log_time_ns: int
    data: bytes
    decoded: Any
    qos_yaml: str


def read_with_mcap(path: Path) -> list[McapMessage]:
    """Every message of a rosbag2 directory (its .mcap files) or a bare .mcap, decoded, with
    every chunk and data-section checksum present and verified."""
    path = Path(path)
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    assert files, f"no .mcap in {path}"
    out: list[McapMessage] = []
    for file in files:
        with file.open("rb") as f:
            chunks = [
                r for r in StreamReader(f, emit_chunks=True, validate_crcs=True).records
                if isinstance(r, Chunk | DataEnd)
            ]  # fmt: skip
            # BagWriter fills in the checksums the rosbags writer leaves at 0: all checked
            assert chunks and all(
                (r.uncompressed_crc if isinstance(r, Chunk) else r.data_section_crc) != 0
                for r in chunks
            ), f"{file}: a chunk or the data section has no checksum"
            f.seek(0)
            reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages(
                log_time_order=True
            ):
                out.append(
                    McapMessage(
                        channel.topic,
                        schema.name if schema else "",
                        message.log_time,
                        bytes(message.data),
                        decoded,
                        channel.metadata.get("offered_qos_profiles", ""),
                    )
                )
    return out


@pytest.fixture
def mcap_read() -> Callable[[Path], list[McapMessage]]:
    """The independent MCAP reader as a fixture (see read_with_mcap)."""
    return read_with_mcap


#: Runs argv[1:] with RLIMIT_FSIZE = argv[0] bytes and SIGXFSZ ignored (both survive exec).
_LIMIT_FILES = (
    "import os, resource, signal, sys\n"
    "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
    "limit = int(sys.argv[1])\n"
    "resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def file_size_limited(
    argv: list[str], limit: int, **kw: Any
) -> subprocess.CompletedProcess | subprocess.Popen:
    """Run ``python *argv`` where no file can grow past ``limit`` bytes: a write beyond it
    fails with OSError EFBIG ("File too large"), as a write to a full disk fails with
    ENOSPC, without a small filesystem to mount. ``popen=True`` starts it (stdout and
    stderr piped, text) instead of waiting for it."""
    cmd = [sys.executable, "-c", _LIMIT_FILES, str(limit), sys.executable, *argv]
    if kw.pop("popen", False):
        return subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw
        )
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, **kw)


@pytest.fixture
def limited_run() -> Callable[..., Any]:
    """:func:`file_size_limited` as a fixture."""
    return file_size_limited
