"""``recslam dashboard``: serve the viser dashboard for a recorded map or the synthetic demo.

``--replay FILE`` reads a map recording (``common.map_view.save_recording``); ``--demo``
builds the synthetic three-robot room; ``--record FILE`` with ``--demo`` writes that map as a
recording and exits. ``--reveal SECONDS`` grows the map progressively, as it would live.
"""

from __future__ import annotations

import argparse
import logging
import time

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dashboard",
        help="serve the live-map dashboard (viser) for a recorded or synthetic map",
        description=__doc__,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--replay", metavar="FILE", help="map recording (.npz) to show")
    src.add_argument("--demo", action="store_true", help="synthetic three-robot room")
    p.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    p.add_argument(
        "--open", action="store_true", help="no access token (anyone who reaches it may view)"
    )
    p.add_argument("--points", type=int, default=30_000, help="--demo: map points (30000)")
    p.add_argument(
        "--reveal",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="reveal the map progressively over this many seconds (default: at once)",
    )
    p.add_argument("--record", metavar="FILE", help="--demo: write the map as a recording, exit")
    p.add_argument(
        "--seconds",
        type=float,
        default=0.0,
        help="stop after this many seconds (default: run until Ctrl-C)",
    )
    p.set_defaults(func=handler)


def handler(args: argparse.Namespace) -> int:
    from common.map_view import MapViewError, StaticMapSource, load_recording, save_recording
    from dashboard.demo import DemoConfig, make_demo_map
    from dashboard.viewer import Dashboard, DashboardConfig, DashboardError, new_access_token

    try:
        if args.demo:
            delta, stats = make_demo_map(DemoConfig(n_points=args.points))
            if args.record:
                save_recording(args.record, delta, stats)
                print(
                    f"wrote {args.record}: {len(delta.points)} points, "
                    f"{len(delta.keyframes)} keyframes"
                )
                return 0
        else:
            if args.record:
                print("error: --record needs --demo")
                return 2
            delta, stats = load_recording(args.replay)
        source = StaticMapSource(delta, stats, reveal_seconds=args.reveal)
        token = None if args.open else new_access_token()
        dash = Dashboard(source, DashboardConfig(args.host, args.port, token)).start()
    except (MapViewError, DashboardError) as exc:
        print(f"error: {exc}")
        return 2
    print(
        f"dashboard at {dash.url} (from another machine: ssh -L {args.port}:localhost:"
        f"{args.port} HOST, then open this URL with localhost); Ctrl-C stops"
    )
    try:
        t_end = time.monotonic() + args.seconds if args.seconds > 0 else float("inf")
        while time.monotonic() < t_end:
            time.sleep(min(0.5, max(t_end - time.monotonic(), 0.0)))
    except KeyboardInterrupt:
        pass
    finally:
        dash.stop()
    return 0
