"""owl_diag: print ``/diagnostics`` of a running node as a table (no ros2cli needed).

    owl_diag --once                 # the first DiagnosticArray that arrives, then exit
    owl_diag                        # every array as it arrives, until Ctrl-C
    owl_diag --name owl: --values   # only statuses whose name starts with "owl:", with keys

One block per DiagnosticArray: a line with its stamp, then one row per status (level,
name, hardware_id, message) and, with ``--values``, its key/value pairs indented below.
The subscription is best effort (it matches reliable and best-effort publishers). When
nothing arrives within ``--timeout`` seconds: one line on stderr naming the topic, exit 1.
ROS arguments (``--ros-args -r /diagnostics:=/other``, a domain through ROS_DOMAIN_ID)
pass through.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, TextIO

from bags.cli import OneLineErrorParser
from bags.cli.replay import split_ros_args
from msg_adapters.diagnostics import StatusRecord, msg_to_records

PROG = "owl_diag"
LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def build_parser() -> Any:
    """The command-line interface."""
    p = OneLineErrorParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--topic", default="/diagnostics", help="topic (default /diagnostics)")
    p.add_argument("--once", action="store_true", help="print one array, then exit")
    p.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="give up after S seconds without a message, exit 1 (default 10; 0 = never)",
    )
    p.add_argument("--name", default="", help="only statuses whose name starts with this")
    p.add_argument("--values", action="store_true", help="also print the key/value pairs")
    return p


def table(stamp_ns: int, records: Sequence[StatusRecord], values: bool = False) -> list[str]:
    """The lines printed for one DiagnosticArray."""
    rows = [(LEVELS.get(int(r.level), str(int(r.level))), r.name, r.hardware_id, r.message)
            for r in records]  # fmt: skip
    head = ("LEVEL", "NAME", "HARDWARE_ID", "MESSAGE")
    widths = [max(len(str(x[i])) for x in [head, *rows]) for i in range(3)]
    out = [f"--- {stamp_ns * 1e-9:.3f} s, {len(records)} statuses"]
    out.append(
        "  ".join(h.ljust(w) for h, w in zip(head[:3], widths, strict=True)) + "  " + head[3]
    )
    for row, rec in zip(rows, records, strict=True):
        out.append("  ".join(str(c).ljust(w) for c, w in zip(row[:3], widths, strict=True))
                   + "  " + row[3])  # fmt: skip
        if values:
            key_w = max((len(k) for k, _ in rec.values), default=0)
            out += [f"    {k.ljust(key_w)}  {v}" for k, v in rec.values]
    return out


def run(
    topic: str,
    once: bool,
    timeout_s: float,
    name_prefix: str = "",
    values: bool = False,
    ros_args: Sequence[str] = (),
    out: TextIO = sys.stdout,
) -> int:
    """Subscribe and print; returns the exit status (1 on timeout)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=[PROG, *ros_args], context=context,
               signal_handler_options=SignalHandlerOptions.NO)  # fmt: skip
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    node = rclpy.create_node("owl_diag", context=context, start_parameter_services=False)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    got = [0]
    last = [time.monotonic()]

    def on_msg(msg: Any) -> None:
        stamp, records = msg_to_records(msg)
        records = [r for r in records if r.name.startswith(name_prefix)]
        if not records:
            return
        got[0] += 1
        last[0] = time.monotonic()
        out.write("\n".join(table(stamp, records, values)) + "\n")
        out.flush()
        if once:
            stop.set()

    qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT
    )
    sub = node.create_subscription(DiagnosticArray, topic, on_msg, qos)
    resolved = sub.topic_name
    status = 0
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if timeout_s > 0 and time.monotonic() - last[0] > timeout_s:
                what = "nothing" if got[0] == 0 else "nothing more"
                which = f" with a status name starting {name_prefix!r}" if name_prefix else ""
                print(
                    f"{PROG}: error: {what} on {resolved}{which} within {timeout_s:g} s "
                    "(is the node running, on this ROS_DOMAIN_ID?)",
                    file=sys.stderr,
                )
                status = 1
                break
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_diag``; returns the exit status."""
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(own)
    if not args.timeout >= 0:
        print(
            f"{PROG}: error: --timeout must be >= 0 seconds, got {args.timeout}", file=sys.stderr
        )
        return 2
    try:
        return run(args.topic, args.once, args.timeout, args.name, args.values, ros_args)
    except BrokenPipeError:  # owl_diag | head
        return 0


if __name__ == "__main__":
    sys.exit(main())
