"""owl_replay BAG: publish a bag's messages on live topics, as their recorded CDR bytes.

Messages go out exactly as stored (rclpy ``Publisher.publish`` accepts serialised bytes:
no deserialisation, no re-serialisation), in log-time order, at the recorded pace divided
by ``--rate``'s speed-up. ``--clock`` also publishes ``/clock`` (rosgraph_msgs/Clock) with
the bag time, for nodes running with ``use_sim_time``.

QoS offered (what a sensor driver offers, so every subscriber matches):

- topics recorded as transient local (``/tf_static``): reliable, transient local, keep
  last max(1, message count) (up to 100), so late subscribers still get every transform;
- all other topics: reliable, volatile, keep last ``--qos-depth`` (default 100).
  A reliable publisher matches both reliable and best-effort subscriptions;
- ``/clock``: reliable, volatile, keep last 1 (rclpy's time source subscribes best effort).

Large images: unless another RMW or a Fast DDS configuration is chosen in the environment,
the player's Fast DDS gets a 16 MiB shared-memory segment (:mod:`bags.dds`; the default
512 KiB sends larger images, e.g. 720p, over UDP loopback, where a busy subscriber loses
them).

Exit status: 0 after the last message (or Ctrl-C / SIGTERM), 1 on a bag or type error,
2 on bad options; errors are one line on stderr.

Usage::

    python -m bags.cli.replay scene_bag --rate 0.5 --clock --topics /camera/image_raw /imu/data \\
        --remap /camera/image_raw:=/image
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TextIO

from bags.cli import StopRequest, topic_name_problem
from bags.dds import prefer_large_image_profile
from bags.errors import BagError
from bags.io import BagReader, TopicInfo
from msg_adapters.errors import AdapterError
from msg_adapters.msgtypes import message_class
from msg_adapters.stamps import ns_to_stamp

PROG = "owl_replay"
#: /clock publication rate while waiting between messages, Hz.
DEFAULT_CLOCK_HZ = 100.0
#: longest wait for subscribers to acknowledge the last messages before exiting, seconds.
ACK_TIMEOUT_S = 5.0
#: default --start-delay after --wait-for-subscribers, seconds: the publisher sees the match
#: before a best-effort reader has matched the new writer, and what is sent in between is
#: lost (the first 5-6 frames in about one run in five here without it; cf. `ros2 bag play
#: --delay`).
MATCH_SETTLE_S = 0.5


class ReplayError(Exception):
    """A bad option value or a bag that cannot be replayed (one-line message)."""


@dataclass(frozen=True)
class ReplayOptions:
    """Parsed command line.

    Attributes:
        bag: bag path.
        rate: playback speed factor (> 0; 2 = twice as fast).
        loop: start again after the last message.
        clock: publish /clock with the bag time.
        clock_hz: /clock rate while waiting, Hz.
        topics: bag topics to play (None = all).
        remap: bag topic -> published topic.
        start_delay_s: wait this long after creating the publishers (after the
            subscribers matched, with ``wait_for_subscribers``), seconds.
        wait_for_subscribers: wait until every published topic has a matched subscriber.
        wait_timeout_s: give up waiting for subscribers after this long (error), seconds.
        qos_depth: keep-last depth of the volatile publishers.
        quiet: no progress line.
    """

    bag: str
    rate: float = 1.0
    loop: bool = False
    clock: bool = False
    clock_hz: float = DEFAULT_CLOCK_HZ
    topics: tuple[str, ...] | None = None
    remap: tuple[tuple[str, str], ...] = ()
    start_delay_s: float = 0.0
    wait_for_subscribers: bool = False
    wait_timeout_s: float = 30.0
    qos_depth: int = 100
    quiet: bool = False


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Publish a rosbag2 bag's messages on live ROS 2 topics as their recorded "
        "CDR bytes, at the recorded pace.",
    )
    parser.add_argument("bag", help="rosbag2 directory (metadata.yaml + .mcap) or .mcap file")
    parser.add_argument(
        "-r", "--rate", type=float, default=1.0, help="speed factor (default 1: recorded pace)"
    )
    parser.add_argument("-l", "--loop", action="store_true", help="play again after the end")
    parser.add_argument(
        "--clock", action="store_true", help="publish /clock with the bag time (use_sim_time)"
    )
    parser.add_argument(
        "--clock-hz",
        type=float,
        default=DEFAULT_CLOCK_HZ,
        help=f"/clock rate between messages, Hz (default {DEFAULT_CLOCK_HZ:g})",
    )
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics")
    parser.add_argument(
        "--remap",
        nargs="+",
        default=[],
        metavar="FROM:=TO",
        help="publish bag topic FROM on topic TO",
    )
    parser.add_argument(
        "--start-delay",
        type=float,
        default=None,
        metavar="S",
        help=f"seconds to wait after creating publishers (discovery), default 0, or "
        f"{MATCH_SETTLE_S:g} after --wait-for-subscribers",
    )
    parser.add_argument(
        "--wait-for-subscribers",
        action="store_true",
        help="start only when every published topic has a matched subscriber, then wait "
        "--start-delay (a best-effort subscriber matches the new publisher a moment after "
        "the publisher matched it, and drops what arrives before)",
    )
    parser.add_argument(
        "--wait-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="error if subscribers are missing after S seconds (default 30)",
    )
    parser.add_argument(
        "--qos-depth", type=int, default=100, help="keep-last depth of publishers (default 100)"
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    return parser


def _topic_name(name: str, what: str) -> str:
    if not name or any(c.isspace() for c in name):
        raise ReplayError(f"invalid {what} topic name {name!r}")
    full = name if name.startswith("/") else "/" + name
    problem = topic_name_problem(full)
    if problem is not None:  # rclpy would refuse it when creating the publisher
        raise ReplayError(f"invalid {what} topic name {name!r}: {problem}")
    return full


def parse_options(argv: Sequence[str]) -> ReplayOptions:
    """Command line (without ROS arguments) -> ReplayOptions; ReplayError on bad values."""
    ns = _parser().parse_args(list(argv))
    if not ns.rate > 0 or ns.rate == float("inf"):
        raise ReplayError(f"--rate must be a positive number, got {ns.rate}")
    if not ns.clock_hz > 0 or ns.clock_hz == float("inf"):
        raise ReplayError(f"--clock-hz must be a positive number, got {ns.clock_hz}")
    if ns.start_delay is None:
        ns.start_delay = MATCH_SETTLE_S if ns.wait_for_subscribers else 0.0
    if not ns.start_delay >= 0:
        raise ReplayError(f"--start-delay must be >= 0 seconds, got {ns.start_delay}")
    if not ns.wait_timeout > 0:
        raise ReplayError(f"--wait-timeout must be > 0 seconds, got {ns.wait_timeout}")
    if ns.qos_depth < 1:
        raise ReplayError(f"--qos-depth must be >= 1, got {ns.qos_depth}")
    remap = []
    for item in ns.remap:
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise ReplayError(f"--remap expects FROM:=TO, got {item!r}")
        remap.append((_topic_name(src, "--remap"), _topic_name(dst, "--remap")))
    topics = None if ns.topics is None else tuple(_topic_name(t, "--topics") for t in ns.topics)
    return ReplayOptions(
        bag=ns.bag,
        rate=float(ns.rate),
        loop=ns.loop,
        clock=ns.clock,
        clock_hz=float(ns.clock_hz),
        topics=topics,
        remap=tuple(remap),
        start_delay_s=float(ns.start_delay),
        wait_for_subscribers=ns.wait_for_subscribers,
        wait_timeout_s=float(ns.wait_timeout),
        qos_depth=int(ns.qos_depth),
        quiet=ns.quiet,
    )


def publisher_qos(info: TopicInfo, depth: int) -> Any:
    """The QoS owl_replay offers for a bag topic (see module doc)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    latched = info.qos_kind == "latched"
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=min(max(1, info.count), 100) if latched else depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class _Progress:
    """One self-overwriting status line on a terminal; otherwise a line every 10 s and at
    the end of each loop."""

    def __init__(self, stream: TextIO, quiet: bool, total_msgs: int, span_s: float) -> None:
        self.stream = stream
        self.quiet = quiet
        self.tty = stream.isatty()
        self.total = total_msgs
        self.span = span_s
        self.last = 0.0

    def update(self, bag_s: float, sent: int, loop: int, force: bool = False) -> None:
        now = time.monotonic()
        if self.quiet or (not force and now - self.last < (0.25 if self.tty else 10.0)):
            return
        self.last = now
        text = f"[{PROG}] {bag_s:7.2f}/{self.span:.2f} s  {sent}/{self.total} msgs"
        if loop:
            text += f"  loop {loop + 1}"
        self.stream.write(("\r" + text + "\x1b[K") if self.tty else text + "\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.tty and not self.quiet and self.last:
            self.stream.write("\n")
            self.stream.flush()


def _resolve(
    bag: BagReader, opts: ReplayOptions, stream: TextIO
) -> tuple[list[str], dict[str, str], dict[str, Any]]:
    """Selected bag topics, their output names and message classes (errors before DDS).

    A topic whose message package is not installed (no rclpy class) is an error when it
    was asked for with --topics, and is skipped with one warning line otherwise.
    """
    topics = bag.topics
    selected = list(opts.topics) if opts.topics is not None else sorted(topics)
    for name in selected:
        if name not in topics:
            raise ReplayError(
                f"topic {name} is not in bag {opts.bag} (has: {', '.join(sorted(topics))})"
            )
    classes = {}
    for name in list(selected):
        try:
            classes[name] = message_class(topics[name].msgtype)
        except AdapterError as err:
            if opts.topics is not None:
                raise ReplayError(f"topic {name}: {err}") from None
            stream.write(f"[{PROG}] skipping {name}: {err}\n")
            selected.remove(name)
    remap = dict(opts.remap)
    for src in remap:
        if src not in selected:
            raise ReplayError(f"--remap source {src} is not a played topic of {opts.bag}")
    outputs = {t: remap.get(t, t) for t in selected}
    if len(set(outputs.values())) != len(outputs):
        raise ReplayError(f"--remap maps two topics onto one: {sorted(outputs.values())}")
    return selected, outputs, classes


def _wait_for_subscribers(
    publishers: dict[str, Any], opts: ReplayOptions, stop: StopRequest
) -> None:
    deadline = time.monotonic() + opts.wait_timeout_s
    while not stop.requested:
        missing = [t for t, pub in publishers.items() if pub.get_subscription_count() < 1]
        if not missing:
            return
        if time.monotonic() > deadline:
            raise ReplayError(
                f"no subscriber on {', '.join(missing)} after {opts.wait_timeout_s:g} s"
            )
        time.sleep(0.02)


def replay(opts: ReplayOptions, ros_args: Sequence[str] = (), stream: TextIO = sys.stderr) -> int:
    """Play the bag; returns the number of messages published.

    Raises:
        BagError: missing, non-bag, truncated or corrupt bag.
        ReplayError: unknown topic or type, subscribers missing after the timeout.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock

    with BagReader(opts.bag) as bag:
        selected, outputs, classes = _resolve(bag, opts, stream)
        infos = bag.topics
        start_ns, end_ns = bag.start_ns, bag.end_ns
        total = sum(infos[t].count for t in selected)
        stop = StopRequest()
        old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
        context = Context()
        prefer_large_image_profile()
        rclpy.init(
            args=[PROG, *ros_args],
            context=context,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        node = None
        progress = _Progress(stream, opts.quiet, total, (end_ns - start_ns) / 1e9)
        sent = 0
        try:
            node = rclpy.create_node(PROG, context=context)
            publishers = {
                outputs[t]: node.create_publisher(
                    classes[t], outputs[t], publisher_qos(infos[t], opts.qos_depth)
                )
                for t in selected
            }
            by_topic = {t: publishers[outputs[t]] for t in selected}
            clock_pub = None
            if opts.clock:
                clock_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
                clock_pub = node.create_publisher(Clock, "/clock", clock_qos)
            if opts.wait_for_subscribers:
                _wait_for_subscribers(publishers, opts, stop)
            _sleep_until(time.monotonic() + opts.start_delay_s, stop)
            loop = 0
            clock_period = 1.0 / opts.clock_hz
            while not stop.requested:
                wall0 = time.monotonic()
                next_clock = wall0

                def publish_clock(bag_ns: int, pub: Any = clock_pub) -> None:
                    if pub is not None:
                        pub.publish(Clock(clock=ns_to_stamp(bag_ns)))

                publish_clock(start_ns)
                for raw in bag.messages(selected):
                    due = wall0 + (raw.log_time_ns - start_ns) / 1e9 / opts.rate
                    while not stop.requested:
                        now = time.monotonic()
                        if now >= due:
                            break
                        if clock_pub is not None and now >= next_clock:
                            publish_clock(start_ns + int((now - wall0) * opts.rate * 1e9))
                            next_clock = now + clock_period
                        wake = min(due, next_clock) if clock_pub is not None else due
                        time.sleep(min(max(wake - now, 0.0), 0.05))
                        progress.update((now - wall0) * opts.rate, sent, loop)
                    if stop.requested:
                        break
                    publish_clock(raw.log_time_ns)
                    by_topic[raw.topic].publish(raw.data)
                    sent += 1
                    progress.update((raw.log_time_ns - start_ns) / 1e9, sent, loop)
                if not opts.loop or total == 0:
                    break
                progress.update((end_ns - start_ns) / 1e9, sent, loop, force=True)
                loop += 1
            progress.update((end_ns - start_ns) / 1e9, sent, loop, force=True)
            progress.finish()
            # Reliable delivery of the last messages: wait for every matched subscriber to
            # acknowledge before the publishers are destroyed (best effort ones ack at once).
            if not stop.requested:
                for pub in [*publishers.values(), *([clock_pub] if clock_pub else [])]:
                    pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown(context=context)
            for sig, handler in old.items():
                signal.signal(sig, handler)
    return sent


def _sleep_until(deadline: float, stop: StopRequest) -> None:
    while not stop.requested:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, 0.05))


def split_ros_args(args: Sequence[str]) -> tuple[list[str], list[str]]:
    """(own arguments, ROS arguments): every ``--ros-args ... [--]`` block goes to ROS.

    Unlike rclpy's remove_ros_args this leaves ``FROM:=TO`` outside ``--ros-args`` alone
    (rcl would take it for a deprecated remap rule), so ``--remap FROM:=TO`` is ours.
    """
    own: list[str] = []
    ros: list[str] = []
    in_ros = False
    for arg in args:
        if arg == "--ros-args":
            in_ros = True
            ros.append(arg)
        elif in_ros and arg == "--":
            in_ros = False
            ros.append(arg)
        else:
            (ros if in_ros else own).append(arg)
    return own, ros


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point (owl_replay = bags.cli.replay:main)."""
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    try:
        opts = parse_options(own)
    except ReplayError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    try:
        sent = replay(opts, ros_args)
    except (BagError, ReplayError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    if not opts.quiet:
        print(f"[{PROG}] published {sent} messages", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
