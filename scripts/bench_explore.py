"""How fast the explorer's page follows a slider, measured in a real browser (issue #29: slider
change -> updated view, a 256 x 256 map plus the curves, in at most 100 ms).

Starts ``pbrdf-cl explore`` on a free port, opens the page in headless chromium (Selenium; Debian's
chromium and chromedriver), and presses the arrow keys on the n slider: each press moves n by one
step.  For each press it records, in the browser, the time from just before the key event is sent
to the next animation frame after both the map's and set A's curves' data have arrived from the
server (so: the key event, the websocket round trip, the server's computation of the curves and the
256 x 256 map, the transfer and BokehJS's update; the paint of that frame is not included).  Then
the same while a Sobol' map and a fit run in the background, to see that the sliders stay live;
with ``--load`` instead the same again while N processes (default: one per core) keep the cores
busy (issue #37: p90 at most 100 ms under that load).

    python scripts/bench_explore.py [--presses 40] [--quantity dop] [--sets 1] [--load [N]]

Prints the latencies (median, 90th percentile, max) and the server's own compute time per update
(the page's "views updated in ... ms" line).  Not a test: the numbers depend on the machine's load.

    python scripts/bench_explore.py --loads 500 [--client bokeh|browser] [--every 50]

The server's memory over many pages (issue #39: a server that stays up for a day): opens the page
and closes it ``--loads`` times, one after the other, and prints the server's RSS every ``--every``
loads, then once the closed pages' sessions have had time to be released.  ``--client bokeh``
(default) opens each page as BokehJS does, over the websocket (``bokeh.client.pull_session``: the
server creates the session and sends the whole document, then the connection closes); ``browser``
loads it in headless chromium and leaves it for ``about:blank`` (slower: the browser's own work).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pbrdf_cl.app import drive  # noqa: E402

ARM = """
window.__pb = window.__pb || {};
const doc = Bokeh.documents[0];
if (!window.__pb.armed) {
  // the websocket's traffic: the slider's patch sent, the server's first message back
  const send = WebSocket.prototype.send;
  WebSocket.prototype.send = function (data) {
    if (!this.__pb) {
      this.__pb = true;
      this.addEventListener('message', (e) => {
        const p = window.__pb;
        if (p.sent !== null && p.got === null) p.got = performance.now();
        if (p.sent !== null && p.bin === null && typeof e.data !== 'string') p.bin = performance.now();
      });
    }
    if (window.__pb.ts !== null && window.__pb.sent === null) window.__pb.sent = performance.now();
    return send.call(this, data);
  };
  for (const name of ['map', 'curve_A']) {
    const m = doc.get_model_by_name(name);
    m.properties.data.change.connect(() => {
      window.__pb[name] = true;
      if (window.__pb.first === null) window.__pb.first = performance.now();
      if (window.__pb.map && window.__pb.curve_A && window.__pb.done === null)
        requestAnimationFrame(() => {
          window.__pb.done = performance.now();
          if (window.__pb.resolve) window.__pb.resolve();
        });
    });
  }
  const slider = Object.values(Object.fromEntries(doc._all_models)).filter(m => m.type == 'Slider')[0];
  slider.properties.value.change.connect(() => { if (window.__pb.ts === null) window.__pb.ts = performance.now(); });
  window.__pb.armed = true;
}
window.__pb.ts = null; window.__pb.sent = null; window.__pb.got = null; window.__pb.bin = null;
window.__pb.first = null;
window.__pb.map = false; window.__pb.curve_A = false; window.__pb.done = null; window.__pb.resolve = null;
window.__pb.t0 = performance.now();
"""


#: The columns of :func:`press_and_time`'s row: the latencies, then the parts of the first one.
COLUMNS = ("slider -> view", "key press -> view", "slider -> patch sent", "patch sent -> first reply",
           "patch sent -> first data frame", "first data frame -> new data", "new data -> next frame")


RESULT = ("[p.done - p.ts, p.done - p.t0, p.sent - p.ts, p.got - p.sent, p.bin - p.sent, p.first - p.bin, "
          "p.done - p.first]")
#: Waits in the browser for the update's frame (no polling): calls back with RESULT, or null.
AWAIT = f"""
const cb = arguments[arguments.length - 1], p = window.__pb;
const give = () => cb({RESULT});
if (p.done !== null) give(); else {{
  p.resolve = give;
  setTimeout(() => {{ if (p.done === null) cb(null); }}, arguments[0]);
}}
"""


def press_and_time(driver, handle, key, timeout=10.0, poll=False):
    """One key press on a slider handle: (ms from the slider's change in the browser, ms from just
    before the key press) to the frame after the update, then the first one's parts (see
    :data:`COLUMNS`: the browser sending the slider's patch; the websocket round trip to the
    server's first message back (its reply to the patch), and to the first binary frame of its
    update (the server's work and the transfer); from there BokehJS receiving the update and
    applying it, to the first of the map's and curves' data; the rest to the next frame); NaN
    where no update came.  The browser calls back once the frame has come; with ``poll`` this
    asks it every 2 ms instead (as the bench did before: each question is WebDriver's round trip
    through chromedriver into the page's main thread, which on a busy machine competes with
    the update it measures)."""
    driver.execute_script(ARM)
    handle.send_keys(key)
    t0 = time.time()
    while time.time() - t0 < timeout:
        if poll:
            done = driver.execute_script(f"const p = window.__pb; return p.done === null ? null : {RESULT}")
            time.sleep(0.002)
        else:
            driver.set_script_timeout(timeout + 5)
            done = driver.execute_async_script(AWAIT, 1e3 * (timeout - (time.time() - t0)))
        if done is not None:
            return tuple(float("nan") if v is None else float(v) for v in done)
    return (float("nan"),) * len(COLUMNS)


def server_ms(driver):
    for el in drive.deep_find(driver, "small"):
        m = re.search(r"views updated in (\d+) ms", el.text)
        if m:
            return float(m.group(1))
    return float("nan")


JOB_RUNNING = ("return Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
               ".some(m => m.type.endsWith('Progress') && m.visible)")


def run(driver, handle, presses, keys, during_job=False, poll=False):
    """``presses`` key presses; with ``during_job`` only those made while the page's progress bar
    shows (a background job runs) are kept, and pressing stops when the job ends."""
    lat, srv = [], []
    for i in range(presses):
        if during_job and not driver.execute_script(JOB_RUNNING):
            break
        lat.append(press_and_time(driver, handle, keys[(i // 5) % 2], poll=poll))
        if during_job:
            if not driver.execute_script(JOB_RUNNING):
                lat.pop()  # the job ended before the view came: not an update during it
                break
            srv.append(float("nan"))
            continue
        time.sleep(0.35)  # the page's timing line follows 250 ms after the views settle
        srv.append(server_ms(driver))
    return np.array(lat).reshape(-1, len(COLUMNS)), np.array(srv)


def report(label, lat, srv):
    ok = lat[np.isfinite(lat[:, 0])]
    if not ok.size:
        print(f"{label}: no update seen")
        return
    a, b = ok[:, 0], ok[:, 1]
    print(f"{label}: {len(ok)} of {len(lat)} updates seen\n"
          f"  slider value changed in the browser -> updated view: median {np.median(a):.1f} ms, "
          f"p90 {np.percentile(a, 90):.1f} ms, max {a.max():.1f} ms\n"
          f"  key press sent by WebDriver -> updated view:          median {np.median(b):.1f} ms, "
          f"p90 {np.percentile(b, 90):.1f} ms, max {b.max():.1f} ms"
          + "\n  the parts, median (p90) ms: " + ", ".join(
              f"{c} {np.nanmedian(ok[:, j]):.1f} ({np.nanpercentile(ok[:, j], 90):.1f})"
              for j, c in enumerate(COLUMNS[2:], 2))
          + (f"\n  the server's computation (the page's 'views updated in'): median {np.nanmedian(srv):.0f} ms"
             if np.isfinite(srv).any() else ""))


@contextlib.contextmanager
def busy(count):
    """``count`` processes that keep a core busy each (a Python loop at the default priority) for
    the ``with`` block: the machine's cores busy with other work."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        time.sleep(1.0)  # running before the first press
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def rss_mb(pid):
    """The resident memory of process ``pid`` in MB (Linux: /proc/PID/status)."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def page_loads(loads, every, client, device=None, settle=60.0):
    """Open and close the page ``loads`` times on one server; print its RSS every ``every`` loads
    and after ``settle`` seconds without pages."""
    proc, url = drive.start_server(extra=["--device", device] if device else ())
    driver = None
    try:
        if client == "browser":
            driver = drive.open_browser()
        else:
            from bokeh.client import pull_session

            from pbrdf_cl.app import upload  # noqa: F401 - its and Panel's models: the pulled document holds them
        print(f"page {url}, {loads} loads through {client}; server RSS at start {rss_mb(proc.pid):.0f} MB",
              flush=True)
        t0 = time.time()
        for i in range(1, loads + 1):
            if driver is not None:
                driver.get(url)
                drive.wait_loaded(driver)
                driver.get("about:blank")  # the page closes: its websocket with it
            else:
                pull_session(url=url).close()
            if i % every == 0 or i == loads:
                print(f"  {i:4d} loads: RSS {rss_mb(proc.pid):6.0f} MB  ({time.time() - t0:.0f} s)", flush=True)
        time.sleep(settle)
        print(f"  {settle:.0f} s after the last page closed: RSS {rss_mb(proc.pid):.0f} MB", flush=True)
    finally:
        if driver is not None:
            driver.quit()
        drive.stop_server(proc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--loads", type=int, default=0,
                    help="open and close the page this many times and print the server's RSS (no latencies)")
    ap.add_argument("--every", type=int, default=50, help="with --loads: print the RSS every this many loads")
    ap.add_argument("--client", choices=("bokeh", "browser"), default="bokeh",
                    help="with --loads: open the pages over Bokeh's websocket client, or in chromium")
    ap.add_argument("--presses", type=int, default=40)
    ap.add_argument("--quantity", default="dop", help="dop, aop (the DOP map with AoP ticks), brdf, s0, s1, s2")
    ap.add_argument("--sets", type=int, default=1, help="parameter sets shown (1-4)")
    ap.add_argument("--device", help="the server's --device")
    ap.add_argument("--load", type=int, nargs="?", const=os.cpu_count(), default=0, metavar="N",
                    help="measure the slider without load, then again with N processes keeping a core busy "
                         "each (default: one per core), side by side; no background jobs")
    ap.add_argument("--poll", action="store_true",
                    help="ask the browser every 2 ms whether the update has come (the bench before issue #37), "
                         "instead of having it call back")
    args = ap.parse_args(argv)
    if not args.loads or args.client == "browser":
        drive.require_browser("bench_explore")
    if args.loads:
        page_loads(args.loads, args.every, args.client, args.device)
        return
    from selenium.webdriver.common.keys import Keys
    with drive.session(extra=["--device", args.device] if args.device else ()) as (driver, url):
        show = "ABCD"[:max(1, min(4, args.sets))]
        driver.get(f"{url}?q={args.quantity}&show={show}")
        drive.wait_loaded(driver)
        handle = drive.deep_find(driver, ".noUi-handle")[0]
        keys = (Keys.ARROW_RIGHT, Keys.ARROW_LEFT)
        run(driver, handle, 4, keys)  # warm-up: first builds, first transfers
        print(f"page {url}, quantity {args.quantity}, {len(show)} set(s) shown, 256 x 256 map + curves")
        report("idle server", *run(driver, handle, args.presses, keys, poll=args.poll))
        if args.load:
            with busy(args.load):
                report(f"idle server, {args.load} busy processes beside it (load average "
                       f"{os.getloadavg()[0]:.1f} at the start)", *run(driver, handle, args.presses, keys,
                                                                         poll=args.poll))
            return
        for label in ("Sobol' map around this set", "Fit"):
            if label == "Fit":
                drive.file_input(driver).send_keys(
                    str(Path(__file__).resolve().parents[1] / "examples" / "steel_435nm.csv"))
                drive.wait(lambda: drive.source_data(driver, "data_points")["x"], 60, what="the measurements")
            t0 = time.time()
            drive.button(driver, label).click()
            drive.wait(lambda: driver.execute_script(JOB_RUNNING), 10, 0.01, what="the progress bar")
            lat, srv = run(driver, handle, 200, keys, during_job=True)
            drive.wait(lambda: not driver.execute_script(JOB_RUNNING), 120, what="the background job")
            report(f"while the {label.split()[0].rstrip('.')} job runs in the background ({time.time() - t0:.1f} s "
                   "from the click to the end)", lat, srv)


if __name__ == "__main__":
    main()
