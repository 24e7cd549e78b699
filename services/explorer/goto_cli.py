"""`smana goto X Y`: send the robot's explorer a goal and follow it until it ends.

Prints the goal's feedback, at most a line a second (distance remaining along the path, an ETA at
the speed made so far, time, recoveries), and how it ended. Exit status: 0 when the goal is
reached (succeeded), 1 when it ends otherwise (aborted, canceled, preempted), is refused, or no
feedback comes for --feedback-timeout seconds; 2 on a bad argument or when no explorer answers.
Ctrl-C (or SIGTERM, SIGHUP) cancels the goal (the robot stops) and exits 1. The explorer may be
exploring (it pauses, then resumes) or run with `explorer.mode = "navigate"`.
"""

from __future__ import annotations

import argparse
import math
import queue
import signal
import sys
import time

import msgpack

from smana.common import keys
from smana.common.cli import config_from_args, make_parser, positive_float, run_command
from smana.common.query import QueryError, request
from smana.common.zenoh_config import open_session

ENDED = ("succeeded", "aborted", "canceled", "preempted")


def finite(text: str) -> float:
    """An argparse type: a finite number (metres or radians)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def goal_id(text: str) -> str:
    """An argparse type: a goal id as the explorer takes it."""
    from smana.services.explorer.navigation import GoalRefused, check_goal_id

    try:
        return check_goal_id(text)
    except GoalRefused as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parser():
    lines = __doc__.strip().splitlines()
    p = make_parser("smana goto", lines[0])
    p.epilog = " ".join(line.strip() for line in lines[1:] if line.strip())
    p.add_argument("x", type=finite, help="goal x (m, the map frame)")
    p.add_argument("y", type=finite, help="goal y (m)")
    p.add_argument("--yaw", type=finite, metavar="RAD", help="heading to face at the goal")
    p.add_argument(
        "--tolerance",
        type=positive_float,
        metavar="M",
        help="how near is near enough (default: explorer.follower.goal_tolerance_m)",
    )
    p.add_argument(
        "--id", type=goal_id, help="the goal's id (1 to 64 printable characters; default: made up)"
    )
    p.add_argument(
        "--feedback-timeout",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="give up (exit 1) after this long without feedback (default 10)",
    )
    return p


def feedback_line(fb: dict) -> str:
    """One line of a goal's feedback: its state, the distance left, an ETA at the mean speed
    made good so far (distance covered / time), the time and the recoveries."""
    d, t = fb.get("distance_remaining_m"), fb.get("navigation_time_s") or 0.0
    line = f"goal {fb.get('id')}: {fb.get('state')}"
    if isinstance(d, int | float) and math.isfinite(d):
        line += f", {d:.2f} m to go"
        start = fb.get("_start_distance_m")
        if fb.get("state") == "active" and start is not None and t > 0 and start - d > 0.05:
            line += f", ETA {d / ((start - d) / t):.0f} s"
    line += f", {t:.1f} s, {fb.get('recoveries', 0)} recoveries"
    if fb.get("reason"):
        line += f" ({fb['reason']})"
    return line


def cli(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    cfg = config_from_args(args)
    robot = cfg.general.robot
    body = {"x": args.x, "y": args.y, "yaw": args.yaw, "tolerance_m": args.tolerance}
    if args.id is not None:
        body["id"] = args.id
    feedback: queue.Queue = queue.Queue()

    def on_feedback(sample) -> None:
        # a zenoh callback: decode and hand over
        try:
            feedback.put(msgpack.unpackb(sample.payload.to_bytes()))
        except Exception:  # noqa: BLE001 - a bad sample is not ours to follow
            pass

    with open_session(cfg.zenoh) as session:
        # subscribed before the goal is sent: its first states are not missed
        sub = session.declare_subscriber(keys.explorer_goal_feedback(robot), on_feedback)
        try:
            try:
                reply = request(session, keys.explorer_goal(robot), body, 10.0)
            except QueryError as exc:
                if exc.kind == "no_reply":
                    print(f"smana goto: {exc}", file=sys.stderr)
                    return 2
                reply = {"accepted": False, "reason": str(exc)}
            if not isinstance(reply, dict) or not reply.get("accepted"):
                why = reply.get("reason") if isinstance(reply, dict) else reply
                print(f"goal refused: {why}")
                return 1
            gid = reply["id"]
            print(f"goal {gid} accepted: ({args.x:g}, {args.y:g})", flush=True)
            # SIGTERM (kill, a closing terminal's SIGHUP) cancels as Ctrl-C does: a goto that
            # ends must not leave its robot driving. SIGINT too, explicitly: a process started
            # with SIGINT ignored (by a parent that ignores it) would keep it ignored, and Ctrl-C
            # would not cancel
            stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
            old = {sig: signal.signal(sig, _interrupt) for sig in stops}
            try:
                return follow(feedback, gid, args.feedback_timeout)
            except KeyboardInterrupt:
                try:
                    r = request(session, keys.explorer_goal_cancel(robot), {"id": gid}, 5.0)
                    print(f"goal {gid}: canceled" if r.get("canceled") else r.get("reason"))
                except QueryError as exc:
                    print(f"goal {gid}: cancel not answered ({exc})")
                return 1
            finally:
                for sig, handler in old.items():
                    signal.signal(sig, handler)
        finally:
            sub.undeclare()


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def follow(feedback: queue.Queue, gid: str, timeout_s: float) -> int:
    """Print the goal's feedback (a line a second, and every change of state) until it ends."""
    last_print = -math.inf
    start = None
    while True:
        try:
            fb = feedback.get(timeout=timeout_s)
        except queue.Empty:
            print(f"goal {gid}: no feedback for {timeout_s:g} s (is the explorer running?)")
            return 1
        if not isinstance(fb, dict) or fb.get("id") != gid:
            continue
        d = fb.get("distance_remaining_m")
        if start is None and isinstance(d, int | float) and math.isfinite(d):
            start = d
        fb["_start_distance_m"] = start
        now = time.monotonic()
        if fb.get("state") in ENDED:
            print(feedback_line(fb), flush=True)
            return 0 if fb["state"] == "succeeded" else 1
        if now - last_print >= 1.0:
            last_print = now
            print(feedback_line(fb), flush=True)


if __name__ == "__main__":
    sys.exit(run_command("goto", cli))
