"""``python -m twin.service.live_view --layout FILE``: write the Foxglove layout of the live view."""

import argparse

from twin.service.live_view.layout import write_layout

ap = argparse.ArgumentParser(prog="python -m twin.service.live_view", description="write the Foxglove layout of the "
                             "live view")
ap.add_argument("--layout", required=True, metavar="FILE", help="where to write it (deploy/foxglove-layout.json)")
print(write_layout(ap.parse_args().layout))
