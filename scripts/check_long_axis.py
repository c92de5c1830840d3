"""A one-axis sweep of 10^7 values into a Zarr store (issue 39): peak RSS and the size of the
metadata files (``.zattrs``, ``.zmetadata``, every ``.zarray``/``.zattrs``).  Not run in CI; the
targets are under 500 MB peak RSS and under 2 MB of metadata.

    python scripts/check_long_axis.py [--points 10000000] [--out /tmp/long.zarr] [--backend numpy]
"""
import argparse
import json
import resource
import shutil
import sys
import time
from pathlib import Path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=10 ** 7)
    p.add_argument("--out", default="long-axis.zarr")
    p.add_argument("--backend", default="auto")
    p.add_argument("--resume", action="store_true", help="run it twice (the second run verifies and skips)")
    args = p.parse_args(argv)
    import pbrdf_cl
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    spec = dict(axes=dict(theta_r=f"0:85@{args.points}"), fixed=dict(theta_i=40, n=1.6, k=2.139, sigma=0.5))
    t0 = time.perf_counter()
    res = pbrdf_cl.sweep(spec, out, progress=False, backend=args.backend)
    runs = [time.perf_counter() - t0]
    if args.resume:
        t0 = time.perf_counter()
        again = pbrdf_cl.sweep(spec, out, progress=False, backend=args.backend)
        assert again.chunks_computed == 0
        runs.append(time.perf_counter() - t0)
    meta = sum(f.stat().st_size for f in out.rglob("*") if f.name in (".zattrs", ".zarray", ".zgroup", ".zmetadata"))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    report = dict(points=args.points, chunks=res.chunks_total, complete=res.complete,
                  seconds=[round(s, 2) for s in runs], peak_rss_mb=round(rss, 1), metadata_bytes=meta,
                  zmetadata_bytes=(out / ".zmetadata").stat().st_size,
                  root_zattrs_bytes=(out / ".zattrs").stat().st_size)
    print(json.dumps(report))
    return 0 if res.complete and rss < 500 and meta < 2 << 20 else 1


if __name__ == "__main__":
    sys.exit(main())
