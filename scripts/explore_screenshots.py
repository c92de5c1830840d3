"""Screenshots of the explorer's views for the docs (``docs/explore_*.png``), taken in headless
chromium: the page opened from URLs that set each state (so each shot is also a check that a link
reopens a view), the example CSVs loaded and fitted (DOP; a polarization camera's s1, s2 under a
source at +45 degrees), a Sobol' map and a design computed.

    python scripts/explore_screenshots.py [--out docs]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pbrdf_cl.app import drive  # noqa: E402

STEEL = "1.6,2.139,0.5,0.9,0.15,-0.3"
ROUGH = "1.6,2.139,0.35,0.9,0.15,-0.3"


def shot(driver, url, path, actions=()):
    driver.get(url)
    drive.wait_loaded(driver)
    for act in actions:
        act(driver)
    time.sleep(1.0)  # the last frame painted
    driver.save_screenshot(str(path))
    print("wrote", path)


def load_and_fit(driver, csv="steel_435nm.csv"):
    drive.file_input(driver).send_keys(str(ROOT / "examples" / csv))
    drive.wait(lambda: drive.source_data(driver, "data_points")["x"], 60, what="the measurements")
    drive.button(driver, "Fit").click()
    drive.wait(lambda: drive.source_data(driver, "fit_table")["value"], 120, what="the fit")


def sobol_and_design(driver):
    drive.button(driver, "Sobol' map around this set").click()
    def drawn():
        image = drive.source_data(driver, "sobol_S1_src")["image"][0]
        return np.isfinite(np.asarray(image, dtype=float)).any()
    drive.wait(drawn, 120, what="the Sobol' map")
    driver.execute_script("Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
                          ".find(m => m.type.endsWith('Select') && m.value == 'n').value = 'kd'")
    drive.wait(lambda: "of kd" in driver.execute_script(
        "return Bokeh.documents[0].get_model_by_name('sobol_S1').title.text"), 30, what="the Sobol' map of kd")
    drive.button(driver, "Design geometries for n, k").click()
    drive.wait(lambda: drive.source_data(driver, "design_points")["x"], 120, what="the design")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    drive.require_browser("explore_screenshots")
    with drive.session(width=1800, height=1700) as (driver, url):
        shot(driver, f"{url}?A={STEEL}&B={ROUGH}&show=AB&q=dop", out / "explore_curves_fit.png", [load_and_fit])
        shot(driver, f"{url}?A={STEEL}&q=aop&map=hemisphere&ti=40", out / "explore_hemisphere_aop.png")
        shot(driver, f"{url}?A={STEEL}&B={ROUGH}&show=AB&q=aop&phi=150&ti=30,50", out / "explore_map_aop_phi150.png")
        shot(driver, f"{url}?A={STEEL}&q=brdf&ti=40", out / "explore_brdf.png")
        shot(driver, f"{url}?A={STEEL}&q=dop", out / "explore_sobol_design.png", [sobol_and_design])
        shot(driver, f"{url}?A={STEEL}&q=s2n&inc=0,1,0", out / "explore_camera_fit.png",
             [lambda d: load_and_fit(d, "steel_camera_45.csv")])


if __name__ == "__main__":
    main()
