"""Reading the files of image stacks and label images: numpy's ``.npz`` archives and netCDF, each
refused in one line naming the file (empty, random bytes, a pickle, a netCDF-4 file without a
library that reads it) instead of a library's message or traceback."""
from __future__ import annotations

import numpy as np


def first_line(exc):
    """An exception's message, its first line only (a library's may run on over several)."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def read_npz(path):
    """Every array of a numpy ``.npz`` archive (name -> array), or a one-line ``ValueError`` naming the
    file where it is none: empty, truncated, random bytes, a pickle or a lone ``.npy``.  Object
    arrays (pickles) are never loaded."""
    import zipfile
    p = str(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
        if not head:
            raise ValueError(f"{p}: the file is empty (0 bytes), not a .npz archive of arrays")
        if head[:2] != b"PK":
            raise ValueError(f"{p}: not a .npz archive of arrays (a .npz is a zip file; this one starts with "
                             f"{head!r}); write it with numpy.savez")
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except ValueError as exc:
        if str(exc).startswith(p):
            raise
        raise ValueError(f"{p}: an array of the .npz archive cannot be read ({first_line(exc)})") from None
    except (OSError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise ValueError(f"{p}: not a readable .npz archive of arrays ({first_line(exc)})") from None


#: The first bytes of a netCDF-3 (classic, 64-bit offset, CDF-5) and a netCDF-4 (HDF5) file.
NETCDF_SIGNATURES = {b"CDF\x01": "netCDF-3", b"CDF\x02": "netCDF-3", b"CDF\x05": "netCDF-3",
                     b"\x89HDF": "netCDF-4 (HDF5)"}


def open_netcdf(path, **kw):
    """``xarray.open_dataset(path, **kw)`` with one line of ours naming the file where it is not
    netCDF (empty, garbage) or where no installed library reads its kind (netCDF-4 needs netCDF4
    or h5netcdf)."""
    import xarray as xr
    p = str(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise ValueError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    kind = NETCDF_SIGNATURES.get(head)
    if kind is None:
        what = ("the file is empty (0 bytes)" if not head else
                f"it starts with {head!r}, neither netCDF-3's signature nor HDF5's")
        raise ValueError(f"{p}: not a netCDF file ({what})")
    try:
        return xr.open_dataset(p, **kw)
    except Exception as exc:  # noqa: BLE001 - the IO backends' many errors: one line of ours
        if kind.startswith("netCDF-4") and "IO backends" in str(exc):
            raise ValueError(f"{p}: a {kind} file, which needs the netCDF4 or h5netcdf package to be read "
                             "(pip install h5netcdf), or write it as netCDF-3 (to_netcdf(format='NETCDF3_64BIT'))"
                             ) from None
        raise ValueError(f"{p}: a {kind} file that cannot be read ({first_line(exc)})") from None


def read_npy(path, what):
    """The array of a numpy ``.npy`` file, or a one-line ``ValueError`` naming ``what`` (the option or
    argument) and the file where it is none (empty, random bytes, a pickle)."""
    p = str(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(6)
        if head != b"\x93NUMPY":
            why = "the file is empty (0 bytes)" if not head else f"it starts with {head!r}, not numpy's signature"
            raise ValueError(f"{what} {p}: not a .npy file ({why}); save the array with numpy.save")
        return np.load(p, allow_pickle=False)
    except ValueError as exc:
        if str(exc).startswith(f"{what} {p}"):
            raise
        raise ValueError(f"{what} {p}: the .npy file cannot be read ({first_line(exc)})") from None
    except (OSError, EOFError) as exc:
        raise ValueError(f"{what} {p}: the .npy file cannot be read ({first_line(exc)})") from None
