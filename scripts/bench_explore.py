"""How fast the explorer's page follows a slider, measured in a real browser (issue #29: slider
change -> updated view, a 256 x 256 map plus the curves, in at most 100 ms).

Starts ``pbrdf-cl explore`` on a free port, opens the page in headless chromium (Selenium; Debian's
chromium and chromedriver), and presses the arrow keys on the n slider: each press moves n by one
step.  For each press it records, in the browser, the time from just before the key event is sent
to the next animation frame after both the map's and set A's curves' data have arrived from the
server (so: the key event, the websocket round trip, the server's computation of the curves and the
256 x 256 map, the transfer and BokehJS's update; the paint of that frame is not included).  Then
the same while a Sobol' map and a fit run in the background, to see that the sliders stay live.

    python scripts/bench_explore.py [--presses 40] [--quantity dop] [--sets 1]

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
import re
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
  for (const name of ['map', 'curve_A']) {
    const m = doc.get_model_by_name(name);
    m.properties.data.change.connect(() => {
      window.__pb[name] = true;
      if (window.__pb.map && window.__pb.curve_A && window.__pb.done === null)
        requestAnimationFrame(() => { window.__pb.done = performance.now(); });
    });
  }
  const slider = Object.values(Object.fromEntries(doc._all_models)).filter(m => m.type == 'Slider')[0];
  slider.properties.value.change.connect(() => { if (window.__pb.ts === null) window.__pb.ts = performance.now(); });
  window.__pb.armed = true;
}
window.__pb.ts = null;
window.__pb.map = false; window.__pb.curve_A = false; window.__pb.done = null;
window.__pb.t0 = performance.now();
"""


def press_and_time(driver, handle, key, timeout=10.0):
    """One key press on a slider handle: (ms from the slider's change in the browser, ms from just
    before the key press) to the frame after the update; NaN where no update came."""
    driver.execute_script(ARM)
    handle.send_keys(key)
    t0 = time.time()
    while time.time() - t0 < timeout:
        done = driver.execute_script("const p = window.__pb; return p.done === null ? null : "
                                     "[p.done - p.ts, p.done - p.t0]")
        if done is not None:
            return tuple(float(v) for v in done)
        time.sleep(0.002)
    return float("nan"), float("nan")


def server_ms(driver):
    for el in drive.deep_find(driver, "small"):
        m = re.search(r"views updated in (\d+) ms", el.text)
        if m:
            return float(m.group(1))
    return float("nan")


JOB_RUNNING = ("return Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
               ".some(m => m.type.endsWith('Progress') && m.visible)")


def run(driver, handle, presses, keys, during_job=False):
    """``presses`` key presses; with ``during_job`` only those made while the page's progress bar
    shows (a background job runs) are kept, and pressing stops when the job ends."""
    lat, srv = [], []
    for i in range(presses):
        if during_job and not driver.execute_script(JOB_RUNNING):
            break
        lat.append(press_and_time(driver, handle, keys[(i // 5) % 2]))
        if during_job:
            if not driver.execute_script(JOB_RUNNING):
                lat.pop()  # the job ended before the view came: not an update during it
                break
            srv.append(float("nan"))
            continue
        time.sleep(0.35)  # the page's timing line follows 250 ms after the views settle
        srv.append(server_ms(driver))
    return np.array(lat).reshape(-1, 2), np.array(srv)


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
          + (f"\n  the server's computation (the page's 'views updated in'): median {np.nanmedian(srv):.0f} ms"
             if np.isfinite(srv).any() else ""))


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
    args = ap.parse_args(argv)
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
        report("idle server", *run(driver, handle, args.presses, keys))
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
