"""Serving the explorer: :func:`explore_app` (one page, for a notebook or a server) and
:func:`serve` (``pbrdf-cl explore``: a local server, opened in the browser)."""
from __future__ import annotations

from . import require_panel


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

    Examples
    --------
    >>> from pbrdf_cl.app.server import serve
    >>> serve(5006, open_browser=False)                         # doctest: +SKIP
    """
    require_panel()
    import panel as pn
    pn.extension()

    def page():
        return explore_app(data, engine=engine)
    server = pn.serve({"explore": page}, port=port, address=address, show=False, start=False,
                      title="pbrdf-cl explore", websocket_origin=[f"{address}:{port}", f"127.0.0.1:{port}",
                                                                  f"localhost:{port}"] if port else "*")
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
