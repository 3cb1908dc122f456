"""Fixtures for bag tests: an independent reader (the `mcap` package + mcap_ros2 decoder).

Every bag written in a test is read back with rosbags (through bags.io) AND with this
reader, so a bag that only rosbags understands would fail.
"""

from __future__ import annotations

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
