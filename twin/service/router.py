"""``python -m twin.service.router ROUTER.json5``: a Zenoh router from a JSON5 file, for hosts without ``zenohd``.

The same router as ``zenohd -c ROUTER.json5`` (eclipse-zenoh's own router
runtime, in router mode, with the file's TLS and access control), run until
SIGINT or SIGTERM. ``deploy/README.md`` uses it to try the site setup on one
machine; production sites run ``zenohd``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading


def main(argv=None) -> int:
    from fpdd.zenohconf import config_endpoints, open_session, zenoh_config
    from fpdd.errors import TwinError

    ap = argparse.ArgumentParser(prog="python -m twin.service.router", description=__doc__.split("\n")[0])
    ap.add_argument("config", help="Zenoh router configuration (JSON5), e.g. deploy/zenoh-router.json5")
    ap.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                    help="listen here instead of the file's endpoints (repeatable)")
    args = ap.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        config = zenoh_config(listen=args.listen, config_file=args.config)
        with open_session(config, "router"):
            listen, _ = config_endpoints(config)
            print(f"router: listening on {', '.join(listen)}", flush=True)
            stop.wait()
    except TwinError as exc:
        print(f"router: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
