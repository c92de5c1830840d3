"""Serving the explorer: :func:`explore_app` (one page, for a notebook or a server) and
:func:`serve` (``pbrdf-cl explore``: a local server, opened in the browser)."""
from __future__ import annotations

import errno

from ..errors import CommandError
from . import require_panel

#: A session whose page has closed (or that no page has connected to yet) is released once it has
#: been unused this long (ms): long enough for a slow browser to connect to the page it loaded;
#: a session released before its page connected is made again when it does.
SESSION_LINGER_MS = 5000
#: How often the server looks for such sessions (ms).
SESSION_CHECK_MS = 1000


def _query_args():
    """The page's URL query (name -> str) in a served session, else {}."""
    import panel as pn
    args = getattr(pn.state, "session_args", None) or {}
    return {k: (v[0].decode() if isinstance(v[0], bytes) else str(v[0])) for k, v in args.items() if v}


def explore_app(data=None, *, engine=None, query=None):
    """The explorer's page: the six parameters on sliders and the live views.

    Parameters
    ----------
    data : str or path, optional
        A measurement CSV to load (as ``pbrdf_cl.read_csv`` reads it).
    engine : pbrdf_cl.Engine, optional
        The engine of the views (default: the default engine), kept for the page's life.
    query : dict, optional
        A URL query (name -> str) to start from; in a served session the page's own URL.

    Returns
    -------
    panel.Row
        The page: display it in a notebook (``pn.extension()`` first) or ``.servable()`` it; its
        ``explorer`` attribute is the :class:`pbrdf_cl.app.page.Explorer` behind it.

    Examples
    --------
    >>> import pbrdf_cl
    >>> page = pbrdf_cl.explore()                               # doctest: +SKIP
    >>> page.explorer.state.sets[0]["n"]                        # doctest: +SKIP
    1.6
    """
    require_panel()
    from .page import Explorer
    explorer = Explorer(engine=engine, data=data, query=query if query is not None else _query_args())
    explorer.layout.explorer = explorer
    return explorer.layout


def origins(address, port):
    """The web origins whose pages may open the explorer's connection: this address and the
    loopback names, at ``port`` only."""
    return list(dict.fromkeys([f"{address}:{port}", f"localhost:{port}", f"127.0.0.1:{port}"]))


def allow_only(server, hosts):
    """Let only ``hosts`` (``name:port``) open a connection to ``server`` (a Bokeh server, bound
    and not yet started): what Bokeh's ``allow_websocket_origin`` sets, written once the port is known."""
    from bokeh.server.tornado import BokehTornado
    app = getattr(server, "_tornado", None)  # Bokeh keeps the application there, not publicly
    if not isinstance(app, BokehTornado):
        raise CommandError("the explorer cannot limit who connects on a free port with this version of Bokeh: "
                           "give the port, --port N")
    app.websocket_origins.clear()
    app.websocket_origins.update(hosts)


def bind_error(exc, address, port):
    """The one line of a server that could not listen on ``address:port`` (``exc``: the OSError)."""
    why = exc.strerror or str(exc)
    if exc.errno == errno.EADDRINUSE:
        return f"port {port} is in use ({why}); choose another with --port N, or --port 0 for a free one"
    if exc.errno == errno.EACCES:
        return f"port {port}: {why} (ports below 1024 need privileges); choose another with --port N, or --port 0"
    return f"cannot listen on {address}{f':{port}' if port else ''}: {why}; check --address and --port"


def make_server(port=0, data=None, engine=None, address="localhost", linger_ms=SESSION_LINGER_MS,
                check_ms=SESSION_CHECK_MS):
    """The explorer's Bokeh server, bound to ``address:port`` and not started (``start()`` it on
    the current IO loop): one page per session at ``/explore``, only its own origins allowed,
    a closed page's session released ``linger_ms`` after its page closed (looked for every
    ``check_ms``), websocket messages up to :data:`.upload.MESSAGE_LIMIT` bytes.  The arguments
    as :func:`serve`'s; raises :class:`pbrdf_cl.CommandError` in one line when the port cannot
    be had."""
    require_panel()
    import panel as pn

    from .upload import MESSAGE_LIMIT
    pn.extension()

    def page():
        return explore_app(data, engine=engine)
    try:  # binds the port now
        server = pn.serve({"explore": page}, port=port, address=address, show=False, start=False,
                          title="pbrdf-cl explore", websocket_origin=origins(address, port) if port else None,
                          websocket_max_message_size=MESSAGE_LIMIT, unused_session_lifetime_milliseconds=linger_ms,
                          check_unused_sessions_milliseconds=check_ms)
    except OSError as exc:
        raise CommandError(bind_error(exc, address, port)) from None
    if not port:  # the free port bound, known only now
        allow_only(server, origins(address, server.port))
    return server


def serve(port=0, data=None, open_browser=True, engine=None, address="localhost"):
    """Serve the explorer on ``address:port`` until interrupted (one page per browser session,
    every session sharing ``engine``).

    Parameters
    ----------
    port : int
        The port (0: any free one).
    data : str or path, optional
        A measurement CSV every new page starts with.
    open_browser : bool
        Open the page in the default browser.
    engine : pbrdf_cl.Engine, optional
        The engine shared by the sessions (default: the default engine).
    address : str
        The address to listen on (default: localhost only).

    Returns
    -------
    None
        Returns when the server stops.

    Raises
    ------
    pbrdf_cl.CommandError
        One line when the port cannot be had (in use: it names the port and says to choose another).

    Notes
    -----
    Only pages served from ``address``, ``localhost`` or ``127.0.0.1`` at the port bound (the
    free one found for ``port=0``) may connect to the server.  A page's session, and what it
    holds, is released :data:`SESSION_LINGER_MS` after the page closes; a file above
    :data:`pbrdf_cl.app.upload.MAX_UPLOAD` bytes is refused by the page before it is sent.

    Examples
    --------
    >>> from pbrdf_cl.app.server import serve
    >>> serve(5006, open_browser=False)                         # doctest: +SKIP
    """
    server = make_server(port, data, engine, address)
    server.start()
    url = f"http://{address}:{server.port}/explore"
    print(f"pbrdf-cl explore: serving {url} (Ctrl-C stops it)", flush=True)
    if open_browser:
        import webbrowser
        server.io_loop.add_callback(lambda: webbrowser.open(url))
    try:
        server.io_loop.start()
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
