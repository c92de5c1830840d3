"""``pbrdf-cl explore``: the interactive explorer, served locally and opened in the browser."""
from __future__ import annotations

from ..errors import CommandError
from .common import device_options, engine_for


def cmd_explore(args) -> int:
    from ..app import require_panel
    require_panel()  # one line naming the extra, before any work
    if args.data:
        from ..io.measurements import read_csv
        try:
            read_csv(args.data)  # a bad file: the same one line as `pbrdf-cl fit`, before serving
        except (OSError, ValueError) as exc:
            raise CommandError(str(exc)) from None
    if not 0 <= args.port <= 65535:
        raise CommandError(f"--port {args.port}: give a port in 0..65535 (0: any free one)")
    engine = engine_for(args)
    from ..app.server import serve
    serve(args.port, data=args.data, open_browser=not args.no_browser, engine=engine, address=args.address)
    return 0


def explore_parser(sub):
    """The `pbrdf-cl explore` sub-command."""
    e = sub.add_parser("explore", help="the interactive explorer: sliders, live curves and maps, fits (a local page)",
                       description="Serve the explorer on a local port and open it in the browser. Needs the "
                       "explore extra: pip install 'pbrdf-cl[explore]'.")
    e.add_argument("--port", type=int, default=5006, help="port to serve on (0: any free one)")
    e.add_argument("--address", default="localhost", help="address to listen on")
    e.add_argument("--data", metavar="CSV", help="a measurement CSV to show (and fit) from the start")
    e.add_argument("--no-browser", action="store_true", help="do not open the page in a browser")
    device_options(e)
    e.set_defaults(func=cmd_explore)
