"""Driving the explorer in a real browser (Selenium with Debian's chromium and chromedriver, or
Chrome): start a server, open the page, find elements inside Panel's shadow DOM, read the data
the plots draw.  Used by ``tests/test_explore_app.py``, ``scripts/bench_explore.py`` and
``scripts/explore_screenshots.py``, each through :func:`session`."""
from __future__ import annotations

import collections
import contextlib
import os
import re
import shutil
import subprocess
import sys
import threading
import time

#: Finds elements matching a CSS selector through every shadow root (Panel renders into them).
DEEP = """
function deep(root, sel, out) {
  root.querySelectorAll(sel).forEach(e => out.push(e));
  root.querySelectorAll('*').forEach(e => { if (e.shadowRoot) deep(e.shadowRoot, sel, out); });
  return out;
}
"""
#: The data of a named ColumnDataSource, arrays as plain lists.
DATA = """
const m = Bokeh.documents[0].get_model_by_name(arguments[0]);
if (!m) return null;
const out = {};
const d = m.data instanceof Map ? Object.fromEntries(m.data) : m.data;
for (const k in d) { const v = d[k]; out[k] = (v && v.length !== undefined && typeof v !== 'string')
    ? Array.from(v, x => (x && x.length !== undefined && typeof x !== 'string') ? Array.from(x) : x) : v; }
return out;
"""


def find_browser():
    """(chromium binary, chromedriver) found on this machine, or None with the reason."""
    binary = next((b for b in (os.environ.get("PBRDF_CHROMIUM"), shutil.which("chromium"),
                               shutil.which("chromium-browser"), shutil.which("google-chrome")) if b), None)
    driver = os.environ.get("PBRDF_CHROMEDRIVER") or shutil.which("chromedriver")
    if binary is None or driver is None:
        return None, "no chromium/chrome and chromedriver on PATH (apt-get install chromium chromium-driver)"
    return (binary, driver), ""


def require_browser(prog):
    """Exit the script ``prog`` with one line naming what is missing where :func:`find_browser`
    finds no browser (before any server starts)."""
    found, why = find_browser()
    if found is None:
        sys.exit(f"{prog}: {why}")


def start_server(data=None, extra=(), timeout=120):
    """Start ``pbrdf-cl explore --port 0 --no-browser`` in a child process; (process, page URL)."""
    cmd = [sys.executable, "-m", "pbrdf_cl", "explore", "--port", "0", "--no-browser", *extra]
    if data:
        cmd += ["--data", str(data)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t0 = time.time()
    lines = []
    while time.time() - t0 < timeout:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            break
        lines.append(line)
        m = re.search(r"serving (http://\S+)", line)
        if m:  # the server's log is read on (and its tail kept) so that a full pipe never blocks it
            proc.log_tail = collections.deque(lines, maxlen=200)
            threading.Thread(target=proc.log_tail.extend, args=(proc.stdout,), daemon=True).start()
            return proc, m.group(1)
    proc.kill()
    raise RuntimeError("the explorer's server did not start: " + "".join(lines)[-2000:])


def open_browser(width=1800, height=1500):
    """A headless chromium driven by Selenium."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    found, why = find_browser()
    if found is None:
        raise RuntimeError(why)
    options = webdriver.ChromeOptions()
    options.binary_location = found[0]
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--hide-scrollbars"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(found[1]), options=options)


@contextlib.contextmanager
def session(data=None, extra=(), width=1800, height=1500, server=None):
    """A served explorer and a browser to drive it: yields (driver, page URL); the browser quits
    and the server is stopped at the end, the server also when the browser does not start.
    ``server``: the (process, URL) of :func:`start_server` already started, instead of starting one."""
    proc, url = server if server is not None else start_server(data, extra)
    try:
        driver = open_browser(width, height)
    except BaseException:
        stop_server(proc)
        raise
    try:
        yield driver, url
    finally:
        driver.quit()
        stop_server(proc)


def stop_server(proc, timeout=10.0):
    """Stop the server of :func:`start_server`: SIGTERM (it exits as on Ctrl-C; coverage, where it
    runs, saves its data), SIGKILL if it has not exited after ``timeout`` seconds."""
    proc.terminate()
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def deep_find(driver, selector):
    """Elements matching ``selector`` anywhere in the page, shadow roots included."""
    return driver.execute_script(DEEP + "return deep(document, arguments[0], []);", selector)


def source_data(driver, name):
    """The data of the ColumnDataSource named ``name`` as the browser holds it (dict of lists)."""
    return driver.execute_script(DATA, name)


def wait(predicate, timeout=60, interval=0.05, what="the page"):
    """Poll ``predicate()`` until it is truthy; its value, or TimeoutError naming ``what``."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"{what}: nothing after {timeout} s")


def wait_loaded(driver, timeout=120):
    """Wait until the page's curves are drawn (the source curve_A holds data)."""
    def ready():
        try:
            d = source_data(driver, "curve_A")
        except Exception:  # noqa: BLE001 - Bokeh not loaded yet
            return None
        return d if d and d.get("ys") else None
    return wait(ready, timeout, what="the explorer's curves")


def file_input(driver, timeout=60):
    """The page's file input (the measurements' *Choose File*), once the browser has drawn it: it
    comes after the curves (its component's module loads in the browser first)."""
    return wait(lambda: deep_find(driver, "input[type=file]"), timeout, what="the file input")[0]


def button(driver, text):
    """The button whose label is ``text``."""
    for b in deep_find(driver, "button"):
        if b.text.strip() == text:
            return b
    raise LookupError(f"no button {text!r} on the page")
