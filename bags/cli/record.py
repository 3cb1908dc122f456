"""owl_record OUT_BAG TOPIC...: record live topics to a rosbag2 MCAP bag until interrupted.

Subscriptions are raw (rclpy ``raw=True`` delivers the CDR bytes as received; nothing is
deserialised), so the bag holds exactly what was published. Each topic's type is taken
from the ROS graph once a publisher appears (topics may appear late; a topic with no
publisher after ``--discovery-timeout`` is reported on stderr and recording goes on).

QoS: the subscription adapts to the publishers it finds, as rosbag2 does: best effort if
any publisher is best effort (else reliable), transient local if every publisher is (so
``/tf_static`` is recorded), keep last ``--qos-depth``. The offered QoS is written to the
bag's metadata ("latched", "sensor" or "reliable" in bags.io terms).

Log time of each message: the receive time (``--stamp receive``, system clock, default)
or the message's header stamp (``--stamp header``; messages whose first field is not a
std_msgs/Header, or whose stamp is negative, fall back to the receive time).

Ends on SIGINT/SIGTERM, after ``--duration`` seconds or ``--max-messages`` messages;
the bag is then closed properly (metadata.yaml + a finished .mcap) and per-topic counts
are printed on stdout. Errors are one line on stderr with a non-zero exit.

A write error (disk full, read-only, I/O error) stops the recording: what was written is
kept (the bag closed with the messages already on disk, or, if even that fails, left as an
unfinished MCAP at OUT_BAG that owl_process and ``BagReader(recover=True)`` read), and the
one error line says which (exit status 1).
"""

from __future__ import annotations

import argparse
import signal
import struct
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TextIO

from bags.cli import StopRequest, topic_name_problem
from bags.cli.replay import split_ros_args
from bags.errors import BagError
from bags.io import BagWriter
from msg_adapters.errors import AdapterError
from msg_adapters.msgtypes import header_first, message_class
from msg_adapters.stamps import NS_PER_S

PROG = "owl_record"


class RecordError(Exception):
    """A bad option value (one-line message)."""


@dataclass(frozen=True)
class RecordOptions:
    """Parsed command line.

    Attributes:
        out: output rosbag2 directory.
        topics: absolute topic names to record.
        overwrite: replace an existing bag at ``out``.
        stamp: "receive" or "header" (log time source).
        discovery_timeout_s: report topics without a publisher after this long, seconds.
        duration_s: stop after this long (None = until interrupted), seconds.
        max_messages: stop after this many messages in total (None = no limit).
        qos_depth: keep-last depth of the subscriptions.
        quiet: no progress line.
    """

    out: str
    topics: tuple[str, ...]
    overwrite: bool = False
    stamp: str = "receive"
    discovery_timeout_s: float = 10.0
    duration_s: float | None = None
    max_messages: int | None = None
    qos_depth: int = 1000
    quiet: bool = False


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Record live ROS 2 topics (raw CDR bytes) to a rosbag2 MCAP bag until "
        "Ctrl-C / SIGTERM.",
    )
    parser.add_argument("out", metavar="OUT_BAG", help="output rosbag2 directory")
    parser.add_argument("topics", nargs="+", metavar="TOPIC", help="topics to record")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT_BAG")
    parser.add_argument(
        "--stamp",
        choices=("receive", "header"),
        default="receive",
        help="log time: receive time (default) or the message header stamp",
    )
    parser.add_argument(
        "--discovery-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="report topics with no publisher after S seconds (default 10)",
    )
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--max-messages", type=int, metavar="N", help="stop after N messages")
    parser.add_argument(
        "--qos-depth", type=int, default=1000, help="subscription queue depth (default 1000)"
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    return parser


def parse_options(argv: Sequence[str]) -> RecordOptions:
    """Command line (without ROS arguments) -> RecordOptions; RecordError on bad values."""
    ns = _parser().parse_args(list(argv))
    topics = []
    for name in ns.topics:
        if not name or any(c.isspace() for c in name) or name.endswith("/"):
            raise RecordError(f"invalid topic name {name!r}")
        full = name if name.startswith("/") else "/" + name
        problem = topic_name_problem(full)
        if problem is not None:  # no publisher could ever appear on it
            raise RecordError(f"invalid topic name {name!r}: {problem}")
        if full in topics:
            raise RecordError(f"topic {full} given twice")
        topics.append(full)
    if not ns.discovery_timeout > 0:
        raise RecordError(f"--discovery-timeout must be > 0 seconds, got {ns.discovery_timeout}")
    if ns.duration is not None and not ns.duration > 0:
        raise RecordError(f"--duration must be > 0 seconds, got {ns.duration}")
    if ns.max_messages is not None and ns.max_messages < 1:
        raise RecordError(f"--max-messages must be >= 1, got {ns.max_messages}")
    if ns.qos_depth < 1:
        raise RecordError(f"--qos-depth must be >= 1, got {ns.qos_depth}")
    return RecordOptions(
        out=ns.out,
        topics=tuple(topics),
        overwrite=ns.overwrite,
        stamp=ns.stamp,
        discovery_timeout_s=float(ns.discovery_timeout),
        duration_s=ns.duration,
        max_messages=ns.max_messages,
        qos_depth=int(ns.qos_depth),
        quiet=ns.quiet,
    )


def header_stamp_ns(data: bytes) -> int | None:
    """The header stamp (int ns) of a CDR message whose first field is std_msgs/Header.

    CDR layout: 4-byte encapsulation header (byte 1: 0 = big endian, 1 = little endian),
    then ``stamp.sec`` (int32) and ``stamp.nanosec`` (uint32). None if too short.
    """
    if len(data) < 12:
        return None
    order = "<" if data[1] & 1 else ">"
    sec, nanosec = struct.unpack_from(order + "iI", data, 4)
    if nanosec >= NS_PER_S:
        return None
    return int(sec) * NS_PER_S + int(nanosec)


def subscription_qos(publisher_infos: Sequence[Any], depth: int) -> tuple[Any, str]:
    """(rclpy QoSProfile that matches every publisher, bags.io qos name for the metadata)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    qos = [info.qos_profile for info in publisher_infos]
    best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in qos)
    latched = bool(qos) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in qos)
    profile = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )
    kind = "latched" if latched else ("sensor" if best_effort else "reliable")
    return profile, kind


class Recorder:
    """Discovers, subscribes and writes; driven by ``run``."""

    def __init__(self, opts: RecordOptions, writer: BagWriter, node: Any, stream: TextIO):
        self.opts = opts
        self.writer = writer
        self.node = node
        self.stream = stream
        self.counts: dict[str, int] = {}
        self.subscriptions: dict[str, Any] = {}
        self.reported_missing = False
        self.total = 0
        #: the error that stopped the recording (the bag cannot be written), else None
        self.failure: BagError | None = None

    def discover(self) -> None:
        """Subscribe to every requested topic that now has a publisher."""
        pending = [t for t in self.opts.topics if t not in self.subscriptions]
        if not pending:
            return
        graph = dict(self.node.get_topic_names_and_types())
        for topic in pending:
            types = graph.get(topic)
            if not types:
                continue
            infos = self.node.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # only subscribers so far: the publisher's QoS is unknown
            msgtype = types[0]
            if len(types) > 1:
                self.say(f"topic {topic} has several types {types}; recording {msgtype}")
            try:
                cls = message_class(msgtype)
            except AdapterError as err:
                self.say(f"not recording {topic}: {err}")
                self.subscriptions[topic] = None
                continue
            qos, kind = subscription_qos(infos, self.opts.qos_depth)
            try:
                self.writer.add_topic(topic, msgtype, qos=kind)
            except BagError as err:
                self.say(f"not recording {topic}: {err}")
                self.subscriptions[topic] = None
                continue
            use_header = self.opts.stamp == "header" and header_first(cls)
            self.counts[topic] = 0
            self.subscriptions[topic] = self.node.create_subscription(
                cls,
                topic,
                lambda data, t=topic, h=use_header: self._on_message(t, data, h),
                qos,
                raw=True,
            )
            self.say(f"recording {topic} ({msgtype}, {kind})")

    def report_missing(self) -> None:
        """Say once which topics still have no publisher."""
        missing = [t for t in self.opts.topics if t not in self.subscriptions]
        if missing and not self.reported_missing:
            self.reported_missing = True
            self.say(
                f"no publisher yet on {', '.join(missing)} after "
                f"{self.opts.discovery_timeout_s:g} s; still waiting"
            )

    def _on_message(self, topic: str, data: bytes, use_header: bool) -> None:
        stamp = time.time_ns()
        if use_header:
            header = header_stamp_ns(data)
            if header is not None and header >= 0:
                stamp = header
        if self.failure is not None:
            return
        try:
            self.writer.write_raw(topic, stamp, data)
        except BagError as err:  # e.g. disk full: stop; closing the bag keeps what was written
            self.failure = err
            return
        self.counts[topic] += 1
        self.total += 1

    def say(self, text: str) -> None:
        """One status line on the stream (unless quiet)."""
        if not self.opts.quiet:
            self.stream.write(f"[{PROG}] {text}\n")
            self.stream.flush()


def record(
    opts: RecordOptions, ros_args: Sequence[str] = (), stream: TextIO = sys.stderr
) -> dict[str, int]:
    """Record until a signal, the duration or the message limit; returns per-topic counts.

    Raises:
        BagError: the output exists (without overwrite) or cannot be written (what was
            recorded before a write error is kept; the message says where).
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    # refuses an existing path early; keep_partial: a write error keeps what was recorded
    writer = BagWriter(opts.out, overwrite=opts.overwrite, keep_partial=True)
    stop = StopRequest()
    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    context = Context()
    rclpy.init(
        args=[PROG, *ros_args], context=context, signal_handler_options=SignalHandlerOptions.NO
    )
    node = None
    try:
        with writer:
            node = rclpy.create_node(PROG, context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            recorder = Recorder(opts, writer, node, stream)
            start = time.monotonic()
            recorder.say(f"recording to {opts.out}: {', '.join(opts.topics)}")
            next_discovery = start
            last_progress = start
            while not stop.requested and recorder.failure is None:
                now = time.monotonic()
                if now >= next_discovery:
                    recorder.discover()
                    next_discovery = now + 0.2
                    if now - start > opts.discovery_timeout_s:
                        recorder.report_missing()
                if opts.duration_s is not None and now - start >= opts.duration_s:
                    break
                if opts.max_messages is not None and recorder.total >= opts.max_messages:
                    break
                executor.spin_once(timeout_sec=0.05)
                if not opts.quiet and stream.isatty() and now - last_progress > 0.5:
                    last_progress = now
                    stream.write(f"\r[{PROG}] {now - start:6.1f} s  {recorder.total} msgs\x1b[K")
                    stream.flush()
            if not opts.quiet and stream.isatty():
                stream.write("\n")
            if recorder.failure is None:
                _drain(executor, recorder)
            # leave the with block normally: BagWriter.close() finishes the MCAP and metadata
            # (after a write error it keeps what was written and raises BagError saying so)
            for sub in recorder.subscriptions.values():
                if sub is not None:
                    node.destroy_subscription(sub)
        if recorder.failure is not None:
            raise recorder.failure
        return dict(recorder.counts)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _drain(executor: Any, recorder: Recorder, limit_s: float = 2.0) -> None:
    """Write what DDS already delivered (acknowledged to the publisher, not yet taken)."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        before = recorder.total
        executor.spin_once(timeout_sec=0.1)
        if recorder.total == before:
            return


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point (owl_record = bags.cli.record:main)."""
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    try:
        opts = parse_options(own)
    except RecordError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    try:
        counts = record(opts, ros_args)
    except BagError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    total = sum(counts.values())
    detail = ", ".join(f"{t}: {n}" for t, n in counts.items()) or "no topics"
    print(f"{PROG}: recorded {total} messages to {opts.out} ({detail})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
