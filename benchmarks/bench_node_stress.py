#!/usr/bin/env python3
"""Stress benchmark of the live ``rotavg_node`` (a benchmark that prints figures, not a test).

What it does
------------
1. Builds the synthetic graph of ``bench_node_stream.py`` (``--nodes`` frames, ``--edges``
   measurements: a chain plus random pairs, noise and gross outliers).
2. Starts ``.venv/bin/rotavg_node`` as a separate process (localhost discovery, its own
   ``ROS_DOMAIN_ID``) with ``solve_period`` ``--solve-period`` and a reduced solver
   (``--extra-node-args``), so that it keeps solving while the edges pour in.
3. Publishes every edge on ``/rotavg_node/edges`` (``TransformStamped``, RELIABLE) from this
   process as fast as the publisher allows: no pacing, one message object refilled per edge.
4. Follows ``/diagnostics`` until the node reports ``edges_received == sent`` (or stops
   making progress), then waits for the solve of the complete graph.
5. Prints: sent, received, ``received == sent`` PASS/FAIL, accepted + rejected, the ingestion
   rate, the solves completed during the load, the CPU time and RSS of the node process and
   of its solver child (``/proc``), and whether the node survived and shut down cleanly.

No loss under a flood: QoS
--------------------------
The subscriptions of the node are RELIABLE with KEEP_LAST history of depth ``qos_depth``. A
reliable KEEP_LAST *reader* whose queue is full drops its oldest sample: the writer has had
its acknowledgement, so nothing is resent. Publishing faster than the node takes edges in
therefore loses edges as soon as more than ``qos_depth`` wait in the node's queue, whatever
the publisher's history. No edge is lost when

* the node's ``qos_depth`` is at least the largest backlog the publisher can build: for a
  burst of N edges published at once, ``qos_depth >= N`` (this script's default:
  ``--qos-depth`` = the number of edges); and
* the publisher is RELIABLE and keeps every unacknowledged edge: KEEP_LAST with depth >= N
  (this script's default) or KEEP_ALL (``--pub-history keep_all``).

The node's default ``qos_depth`` (10000) holds a backlog of 10,000 edges; ``--qos-depth 1000``
shows what happens beyond it. A KEEP_ALL publisher does not prevent that loss (the node's
KEEP_LAST reader still drops), and with Fast DDS 2.14 it stalls: ``publish()`` times out while
its history is full (the script retries; ``--publish-timeout``).

Usage (from the repository root)::

    .venv/bin/python -m benchmarks.bench_node_stress --edges 100000

Helpers (graph, ``/proc`` readings, diagnostics records, node launch) come from
``bench_node_stream.py``.
"""

from __future__ import annotations

import argparse
import math
import shlex
import signal
import sys
import time
from pathlib import Path

from benchmarks.bench_node_stream import (
    NODE_NAME,
    DiagRecord,
    Observer,
    ProcSample,
    add_node_run_arguments,
    begin_run,
    code_version,
    fmt_pf,
    make_graph,
    proc_sample,
    start_node_and_client,
    start_spinner,
    stop_process,
    tail,
    wait_for_match,
    wait_node_idle,
)
from rotavg_ros.core.so3 import matrix_to_quat  # noqa: E402


def descendants(pid: int) -> list[int]:
    """Pids of the processes below ``pid`` (the node's solver child), from ``/proc``."""
    found: list[int] = []
    todo = [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                kids = [int(x) for x in (task / "children").read_text().split()]
            except (OSError, ValueError):
                continue
            found += kids
            todo += kids
    return found


def sample_tree(pid: int) -> dict[int, ProcSample]:
    """``/proc`` samples of ``pid`` and its descendants (the ones still alive)."""
    out = {}
    for p in [pid, *descendants(pid)]:
        s = proc_sample(p)
        if s is not None:
            out[p] = s
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--edges", type=int, default=100_000, help="edges published")
    p.add_argument("--nodes", type=int, default=1000)
    p.add_argument("--solve-period", type=float, default=2.0, help="node's solve_period (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--qos-depth", type=int, default=None,
                   help="node's qos_depth (KEEP_LAST depth of its edge subscriptions); "
                        "default: the number of edges, which guarantees no loss")
    p.add_argument("--pub-history", choices=("keep_last", "keep_all"), default="keep_last",
                   help="history of this process's RELIABLE publisher")
    p.add_argument("--pub-depth", type=int, default=None,
                   help="depth of the publisher's KEEP_LAST history (default: the number of "
                        "edges)")
    p.add_argument("--publish-timeout", type=float, default=600.0,
                   help="stop publishing after this many seconds (a stalled publisher)")
    p.add_argument("--stall-timeout", type=float, default=30.0,
                   help="give up waiting for received == sent after this long without any "
                        "progress in the node's diagnostics")
    add_node_run_arguments(p, hard_timeout=1200.0)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start, deadline, domain_id = begin_run(args)

    graph = make_graph(args.nodes, args.edges, args.seed, 1.0, 0.05)
    E = graph.i.size
    qos_depth = args.qos_depth if args.qos_depth is not None else max(1000, E)
    pub_depth = args.pub_depth if args.pub_depth is not None else E
    print(f"graph: {args.nodes} nodes, {E} measurements on {graph.num_pairs} distinct pairs "
          f"(chain + random), seed {args.seed}")
    node_cmd = [
        args.node_bin, "--ros-args",
        "-p", f"solve_period:={args.solve_period}",
        "-p", f"qos_depth:={qos_depth}",
        *shlex.split(args.extra_node_args),
    ]
    print(f"node: {shlex.join(node_cmd)}")
    print(f"publisher: RELIABLE, {args.pub_history.upper()}"
          + (f" depth {pub_depth}" if args.pub_history == "keep_last" else ""))
    print(f"code: {code_version()}")
    print(f"env: ROS_DOMAIN_ID={domain_id} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    proc, log_path, timer, ctx, node = start_node_and_client(
        node_cmd, args.hard_timeout, domain_id, "bench_node_stress")
    obs = Observer()
    pub_qos = QoSProfile(
        history=(HistoryPolicy.KEEP_ALL if args.pub_history == "keep_all"
                 else HistoryPolicy.KEEP_LAST),
        depth=pub_depth, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(TransformStamped, f"/{NODE_NAME}/edges", pub_qos)
    sub_d = node.create_subscription(
        DiagnosticArray, "/diagnostics", obs.on_diagnostics,
        QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                   reliability=ReliabilityPolicy.RELIABLE))
    ex, stop, spinner = start_spinner(node, ctx)

    rc = 1
    survived = False
    try:
        # ------------------------------------------------------------ start-up
        t_launch = time.monotonic()
        wait_for_match(proc, log_path, min(deadline, t_launch + args.match_timeout),
                       args.match_timeout,
                       lambda: (pub.get_subscription_count() >= 1
                                and sub_d.get_publisher_count() >= 1))
        idle = wait_node_idle(proc, log_path,
                              min(deadline, time.monotonic() + args.match_timeout))
        print(f"matched and idle {time.monotonic() - t_launch:.2f} s after launch "
              f"(start-up CPU {idle.cpu_s:.2f} s)")
        before = sample_tree(proc.pid)

        # ------------------------------------------------------------ flood
        quats = matrix_to_quat(graph.R).tolist()
        frame_i = [graph.ids[k] for k in graph.i.tolist()]
        frame_j = [graph.ids[k] for k in graph.j.tolist()]
        msg = TransformStamped()
        rot = msg.transform.rotation
        sent = failures = 0
        t0 = time.monotonic()
        t_report = t0 + 10.0
        give_up = min(deadline, t0 + args.publish_timeout)

        def publish() -> bool:
            """Publish ``msg``; a full KEEP_ALL history makes publish() time out: retry."""
            nonlocal failures
            while True:
                try:
                    pub.publish(msg)
                    return True
                except Exception as exc:  # noqa: BLE001 - rclpy raises RCLError
                    failures += 1
                    if failures == 1:
                        print(f"publish failed ({exc}); retrying", flush=True)
                    if proc.poll() is not None or time.monotonic() > give_up:
                        return False

        for k in range(E):
            msg.header.frame_id = frame_i[k]
            msg.child_frame_id = frame_j[k]
            rot.x, rot.y, rot.z, rot.w = quats[k]
            if not publish():
                break
            sent += 1
            now = time.monotonic()
            if now > t_report:
                t_report += 10.0
                print(f"  ... {sent} sent after {now - t0:.0f} s ({failures} failed publish "
                      "calls)", flush=True)
                if now > give_up:
                    break
        t_sent = time.monotonic()
        after_send = sample_tree(proc.pid)
        print(f"sent {sent} of {E} edges in {t_sent - t0:.2f} s: "
              f"{sent / (t_sent - t0):.0f} edges/s (publisher as fast as it goes; "
              f"{failures} publish calls failed and were retried)"
              + ("" if sent == E else f"; GAVE UP after --publish-timeout "
                 f"{args.publish_timeout:g} s"))

        # ------------------------------------------------------------ drain
        all_in: DiagRecord | None = None
        final: DiagRecord | None = None
        progress_at, progress = time.monotonic(), -1
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"node exited (rc {proc.returncode}):\n{tail(log_path)}")
            with obs.lock:
                diags = list(obs.diags)
            latest = diags[-1] if diags else None
            if all_in is None:
                all_in = next((d for d in diags
                               if int(d.num("edges_received", -1)) >= sent), None)
            if all_in is not None:
                final = next((d for d in diags if d.t_recv >= all_in.t_recv
                              and int(d.num("edges_received", -1)) >= sent
                              and d.num("solved_version") == d.num("graph_version")), None)
                if final is not None:
                    break
            received_now = int(latest.num("edges_received", -1)) if latest else -1
            if received_now != progress:
                progress_at, progress = time.monotonic(), received_now
            elif time.monotonic() - progress_at > args.stall_timeout:
                print(f"no progress in the node's diagnostics for {args.stall_timeout:g} s: "
                      "giving up waiting")
                break
            time.sleep(0.05)
        end = sample_tree(proc.pid)
        survived = proc.poll() is None

        with obs.lock:
            diags = list(obs.diags)
        if args.verbose:
            print()
            print("diagnostics timeline (recv s after the first send, received, accepted, "
                  "solves completed, last_solve_duration_s, skipped busy):")
            for d in diags:
                print(f"  {d.t_recv - t0:+8.3f} {d.values.get('edges_received')} "
                      f"{d.values.get('edges_accepted')} {d.values.get('solves_completed')} "
                      f"{d.values.get('last_solve_duration_s')} "
                      f"{d.values.get('timer_ticks_skipped_busy')}")

        # ------------------------------------------------------------ report
        rec = final or all_in or (diags[-1] if diags else None)
        print()
        print("== edges (from /diagnostics) ==")
        lost_ok = False
        if rec is None:
            print("no diagnostics received")
        else:
            received = int(rec.num("edges_received", -1))
            accepted = int(rec.num("edges_accepted", -1))
            rejected = int(rec.num("edges_rejected", -1))
            lost_ok = received == sent and accepted + rejected == sent
            print(f"sent {sent}  received {received}  accepted {accepted}  rejected {rejected}"
                  f"  accepted + rejected {accepted + rejected}")
            print(f"received == sent (and accepted + rejected == sent): {fmt_pf(lost_ok)}"
                  + ("" if received == sent else f"  [{sent - received} edges lost]"))

        print()
        print("== ingestion ==")
        if all_in is not None:
            span = all_in.t_recv - t0
            print(f"all {sent} edges in the node {span:.2f} s after the first send: "
                  f"{sent / span:.0f} edges/s overall (a lower bound: the node publishes its "
                  f"diagnostics after each solve, so 'all in' is seen late by up to one "
                  f"period plus one solve)")
        elif rec is not None:
            print(f"the node never reported all {sent} edges (last report: "
                  f"{int(rec.num('edges_received', -1))})")
        during = [d for d in diags if t0 <= d.t_recv and (all_in is None
                                                         or d.t_recv <= all_in.t_recv)]
        backlog = [d for d in during if int(d.num("edges_received", -1)) < sent]
        if len(backlog) >= 2 and backlog[-1].num("edges_received") > backlog[0].num(
                "edges_received"):
            a, b = backlog[0], backlog[-1]
            rate = ((b.num("edges_received") - a.num("edges_received"))
                    / max(b.t_recv - a.t_recv, 1e-9))
            print(f"sustained ingestion while backlogged: {rate:.0f} edges/s (edges_received "
                  f"from {int(a.num('edges_received'))} to {int(b.num('edges_received'))} "
                  f"between diagnostics {b.t_recv - a.t_recv:.2f} s apart)")
        else:
            print("sustained ingestion: too few diagnostics with progress during the load")
        base_solves = 0
        pre = [d for d in diags if d.t_recv < t0]
        if pre:
            base_solves = int(pre[-1].num("solves_completed", 0))
        end_rec = all_in or rec
        if end_rec is not None:
            print(f"solves completed during the load (first send -> all edges in): "
                  f"{int(end_rec.num('solves_completed', 0)) - base_solves}; failed "
                  f"{end_rec.values.get('solves_failed', '?')}; timer ticks skipped busy "
                  f"{end_rec.values.get('timer_ticks_skipped_busy', '?')}")
        if final is not None:
            print(f"solve of the complete graph: {final.values.get('solved_nodes', '?')} nodes, "
                  f"{final.values.get('measurements', '?')} measurements, "
                  f"{final.num('last_solve_duration_s'):.2f} s, depth "
                  f"{final.values.get('depth', '?')}, level {final.level} ({final.message}); "
                  f"diagnostics received {final.t_recv - t0:.2f} s after the first send")
        else:
            print("no solve of the complete graph was seen")

        print()
        print(f"== node process (pid {proc.pid}) and its solver child (/proc) ==")
        node_before, node_end = before.get(proc.pid), end.get(proc.pid)
        node_sent = after_send.get(proc.pid)
        if node_before and node_end and node_sent:
            load_s = node_end.t - node_before.t
            load_cpu = node_end.cpu_s - node_before.cpu_s
            print(f"node CPU: {node_end.cpu_s:.2f} s in total, {load_cpu:.2f} s during the "
                  f"load ({load_s:.1f} s, {100 * load_cpu / load_s:.0f}% of one core; "
                  f"{1e6 * load_cpu / max(sent, 1):.0f} us per edge incl. solves' "
                  f"publishing), of which {node_sent.cpu_s - node_before.cpu_s:.2f} s while "
                  f"publishing")
            print(f"node RSS: {node_before.rss_mb:.0f} MiB before, {node_sent.rss_mb:.0f} MiB "
                  f"after publishing, {node_end.rss_mb:.0f} MiB at the end; peak VmHWM "
                  f"{node_end.hwm_mb:.0f} MiB; threads {node_end.threads}")
        else:
            print("could not read /proc for the node")
        for pid, s in end.items():
            if pid == proc.pid:
                continue
            s0 = before.get(pid)
            during_cpu = s.cpu_s - s0.cpu_s if s0 else math.nan
            print(f"child pid {pid}: CPU {s.cpu_s:.2f} s in total, {during_cpu:.2f} s during "
                  f"the load; RSS {s.rss_mb:.0f} MiB, peak VmHWM {s.hwm_mb:.0f} MiB")
        print(f"node process alive after the load: {fmt_pf(survived)}")

        ok = lost_ok and survived and final is not None
        rc = 0 if ok else 1
        print()
        print(f"SUMMARY: received == sent {fmt_pf(lost_ok)}; node survived {fmt_pf(survived)}; "
              f"complete graph solved {fmt_pf(final is not None)}; wall time "
              f"{time.monotonic() - t_start:.1f} s")
    except RuntimeError as exc:
        print(f"ERROR: {exc}")
        rc = 2
    finally:
        stop.set()
        spinner.join(timeout=5)
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
        how = stop_process(proc, timeout=30.0)
        print(f"node shutdown: {how}")
        clean = proc.returncode in (0, -signal.SIGINT, 130)
        if survived and not clean:
            rc = rc or 1
        if not clean or rc == 2:
            print(f"node log tail ({log_path}):\n{tail(log_path)}")
        else:
            log_path.unlink(missing_ok=True)
        timer.cancel()
    return rc


if __name__ == "__main__":
    sys.exit(main())
