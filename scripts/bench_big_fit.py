#!/usr/bin/env python3
"""Benchmark of fits of big data sets (issue #39): ``pbrdf-cl fit`` end to end, as a user runs it, on
synthetic CSVs of N measurements; prints the seconds, the measurements per second and the peak
resident memory of each run, with the machine's load average beside them.

The data: the DOP of the paper's steel (n 1.6, k 2.139, sigma 0.5, ks 0.9, kd 0.15, c -0.3) by
``pbrdf_cl.dop`` (numpy backend) at N geometries drawn uniformly from theta_i 10..70, theta_r
5..75, phi 120..240 degrees (seeded), plus Gaussian noise of std 0.002 given as dop_std, written
by ``pbrdf_cl.io.measurements.write_csv`` (the examples' writer).  Each fit runs as a child process
(``python -m pbrdf_cl fit CSV --quiet --json OUT``); its peak RSS is the child's own
(``os.wait4``'s ru_maxrss), its CPU time the child's user + system seconds (what a shared machine does not
stretch), its time the wall time of the whole command (reading the CSV, building
or loading the kernels, every stage, writing the JSON)."""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pbrdf_cl
from pbrdf_cl.io.measurements import from_arrays, write_csv

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
NOISE = 0.002


def write_data(path, rows, seed=20260439):
    """A CSV of ``rows`` synthetic measurements (the module docstring's)."""
    rng = np.random.default_rng(seed)
    ti, tr, ph = rng.uniform(10, 70, rows), rng.uniform(5, 75, rows), rng.uniform(120, 240, rows)
    dop = pbrdf_cl.dop(ti, tr, ph, backend="numpy", **STEEL)
    dop = np.clip(dop + rng.normal(0, NOISE, rows), 0, 1)
    write_csv(path, from_arrays(ti, tr, dop, ph, np.full(rows, NOISE)),
              f"{rows} synthetic DOP measurements of the paper's steel ({STEEL}), noise std {NOISE}, seed {seed};\n"
              "written by scripts/bench_big_fit.py")


def run_fit(csv, out_json, extra=()):
    """(seconds, CPU seconds (user + system), peak RSS in bytes, return code, stderr) of ``pbrdf-cl fit``
    on ``csv``."""
    cmd = [sys.executable, "-m", "pbrdf_cl", "fit", str(csv), "--quiet", "--json", str(out_json), *extra]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    return seconds, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024, proc.returncode, err


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", type=int, nargs="+", default=[10_000, 100_000], help="measurements per data set")
    p.add_argument("--repeat", type=int, default=2, help="runs per size (the machine may be shared)")
    p.add_argument("--memory-budget", help="passed to pbrdf-cl fit")
    p.add_argument("--dir", help="keep the CSVs and JSONs here (default: a temporary folder)")
    p.add_argument("--json", help="write the rows of the report here")
    args = p.parse_args(argv)
    extra = ["--memory-budget", args.memory_budget] if args.memory_budget else []
    report = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.dir or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        print(f"{'rows':>9s} {'seconds':>8s} {'rows/s':>8s} {'CPU s':>7s} {'peak RSS':>9s}  load average (1, 5 min) "
              "before")
        for rows in args.rows:
            csv = folder / f"big_fit_{rows}.csv"
            if not csv.exists():
                write_data(csv, rows)
            for _ in range(args.repeat):
                load = os.getloadavg()[:2]
                seconds, cpu, rss, rc, err = run_fit(csv, folder / f"big_fit_{rows}.json", extra)
                if rc != 0:
                    raise SystemExit(f"pbrdf-cl fit of {rows} rows failed (rc {rc}): {err.strip()[-400:]}")
                fit = json.loads((folder / f"big_fit_{rows}.json").read_text())["fits"]["six-param"]
                row = dict(rows=rows, seconds=seconds, rows_per_second=rows / seconds, cpu_seconds=cpu,
                           peak_rss_bytes=rss, load_before=load, x=fit["x"], stage_seconds=fit["seconds"])
                report.append(row)
                print(f"{rows:9d} {seconds:8.1f} {rows / seconds:8.0f} {cpu:7.1f} {rss / 2 ** 20:7.0f} MiB  "
                      f"{load[0]:.2f}, {load[1]:.2f}   n = {fit['x']['n']:.4f}, k = {fit['x']['k']:.4f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
