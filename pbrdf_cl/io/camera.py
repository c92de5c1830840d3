"""From a division-of-focal-plane (DoFP) polarization camera to a polarimetric image stack.

A monochrome DoFP sensor such as Sony's IMX250MZR puts a wire-grid polarizer on every pixel, in
2x2 super-pixels of the angles

    90  45
    135  0

(row 0: 90, 45; row 1: 135, 0 degrees, counted from the sensor's x axis), which is the layout
``polanalyser`` assumes.  :func:`dop_from_frames` demosaics each raw frame (one per illumination
geometry) into the four polarizer images with ``polanalyser.demosaicing``, fits the linear
Stokes vector (S0, S1, S2) per pixel with ``polanalyser.calcStokes`` (Malus' law
I(a) = (S0 + S1 cos 2a + S2 sin 2a) / 2) and takes the degree of linear polarization with
``polanalyser.cvtStokesToDoLP``.  For unpolarised incidence the model's reflected light has S3 = 0
(SPEC.md), so its DoLP is its DOP.  :func:`camera_dataset` keeps S1 and S2 normalised by S0 (``s1``,
``s2``: what a linear polarization camera measures, also under a polarized source, whose state per
frame it takes as ``incident``), adds the geometry and returns the Dataset that a per-pixel
inversion takes.

**Frames.**  The polarizer angles are counted from the sensor's x axis towards its y axis, so S1 and
S2 are in the sensor's frame.  They are the model's (the outgoing beam's s/p frame, SPEC.md) only
where the sensor's x axis is the beam's s axis (perpendicular to the plane of reflection) and its y
axis the beam's p axis: ``roll`` (degrees, the angle from the beam's s axis to the sensor's x axis,
counted from s towards p; per frame or per pixel) rotates them into the beam's frame, and a sensor
mirrored against that sense needs s2 negated.  Without ``roll`` the sensor's frame is taken as the
beam's; the dataset's ``attrs["stokes_frame"]`` says which.

``polanalyser`` (and OpenCV, which it imports but does not declare) is an optional dependency:
``pip install 'pbrdf-cl[camera]'``.
"""
from __future__ import annotations

import numpy as np

from ..compute import pointwise

#: Polarizer angles (degrees) of the four images ``polanalyser.demosaicing`` returns, in order.
POLARIZER_ANGLES = (0.0, 45.0, 90.0, 135.0)
#: The 2x2 super-pixel of the IMX250MZR that polanalyser assumes: polarizer angle at [row, column].
SUPERPIXEL = ((90.0, 45.0), (135.0, 0.0))
#: Demosaicing methods: name -> the name of polanalyser's monochrome conversion code.
DEMOSAIC = {"bilinear": "COLOR_PolarMono", "vng": "COLOR_PolarMono_VNG", "ea": "COLOR_PolarMono_EA"}
#: Pixels of the raw frame that one demosaiced pixel depends on (a square of this side) per method.
_FOOTPRINT = {"bilinear": 3, "vng": 5, "ea": 5}
INSTALL_HINT = "pip install 'pbrdf-cl[camera]'"


def polanalyser():
    """The ``polanalyser`` module, imported on first use.

    Returns
    -------
    module
        ``polanalyser``.

    Raises
    ------
    ImportError
        One line naming ``pip install 'pbrdf-cl[camera]'`` when polanalyser or OpenCV is missing.

    Examples
    --------
    >>> pa = polanalyser()  # doctest: +SKIP
    """
    try:
        import polanalyser as pa
    except ImportError as e:
        missing = getattr(e, "name", None) or "polanalyser"
        raise ImportError(f"the polarization-camera path needs polanalyser and OpenCV ({missing} is not "
                          f"installed): {INSTALL_HINT}") from None
    return pa


def _even_sides(shape):
    """Whether a raw frame of ``shape`` is whole 2x2 super-pixels (even height and width)."""
    return len(shape) == 2 and all(n >= 2 and n % 2 == 0 for n in shape)


def _frames(frames, axis=None, m=None):
    """The raw frames as a list of 2-D arrays of one shape with even sides, or a ValueError.

    One 3-D array holds the frames along its measurement axis: ``axis`` (0, for (M, H, W), or
    -1/2, for (H, W, M) as the outputs have it), else the one of those two readings under which
    every frame is whole super-pixels (even sides) and, where ``m`` (the geometry's measurement
    count) is known, there are ``m`` of them; a shape both readings fit is refused as ambiguous."""
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        raise ValueError(f"frames must be a sequence of 2-D raw frames (one per geometry), got one 2-D array "
                         f"of shape {frames.shape}: wrap it in a list")
    if axis is not None and not (isinstance(frames, np.ndarray) and frames.ndim == 3):
        raise ValueError("axis: only for frames given as one 3-D array (a list holds one frame per geometry)")
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        shape = frames.shape
        if axis is None:
            fits = [a for a in (0, 2) if _even_sides(tuple(n for i, n in enumerate(shape) if i != a))
                    and (m is None or shape[a] == m)]
            if len(fits) != 1:
                count = "" if m is None else f" with {m} measurements (the geometry's)"
                why = ("is ambiguous: it reads as (M, H, W) and as (H, W, M)" if fits else
                       "fits neither (M, H, W) nor (H, W, M) frames of even sides" + count)
                raise ValueError(f"frames: one 3-D array of shape {shape} {why}; say which axis holds the "
                                 "measurements (axis=0 or axis=-1), or pass a list of 2-D raw frames")
            axis = fits[0]
        if axis not in (0, 2, -1):
            raise ValueError(f"axis must be 0 ((M, H, W)) or -1 ((H, W, M)), got {axis!r}")
        frames = list(np.moveaxis(frames, axis, 0))
    out = [np.asarray(f) for f in frames]
    if not out:
        raise ValueError("frames must hold at least one raw frame, got none")
    for i, f in enumerate(out):
        if f.ndim != 2:
            raise ValueError(f"frames[{i}] must be a 2-D raw mosaic, got shape {f.shape}")
        if f.shape != out[0].shape:
            raise ValueError(f"frames[{i}] has shape {f.shape}, frames[0] {out[0].shape}: every frame must have "
                             "one shape")
        if not (np.issubdtype(f.dtype, np.integer) or np.issubdtype(f.dtype, np.floating)):
            raise ValueError(f"frames[{i}] must hold numbers, got dtype {f.dtype}")
    h, w = out[0].shape
    if h % 2 or w % 2 or h < 2 or w < 2:
        raise ValueError(f"frames must have even height and width (whole 2x2 super-pixels), got shape {(h, w)}")
    return out


def _demosaic(pa, raw, method):
    """The four polarizer images (0, 45, 90, 135 degrees) of one raw frame as float64, (4, H, W)."""
    code = getattr(pa, DEMOSAIC[method])
    if np.issubdtype(raw.dtype, np.integer) and raw.dtype not in (np.uint8, np.uint16):
        if raw.min() < 0 or raw.max() > 65535:
            raise ValueError(f"integer frames must hold values in [0, 65535], got [{raw.min()}, {raw.max()}]")
        raw = raw.astype(np.uint16)
    if np.issubdtype(raw.dtype, np.floating) and not np.max(raw) > 0:
        return np.zeros((4,) + raw.shape)   # polanalyser scales float frames by their maximum
    return np.asarray(pa.demosaicing(raw, code), dtype=np.float64)


def dop_from_frames(frames, *, demosaic="bilinear", dark=None, saturation=None, min_intensity=0.0,
                    dtype="float64", axis=None):
    """DOP (DoLP) and intensity S0 image stacks from raw DoFP polarization-camera frames.

    Parameters
    ----------
    frames : sequence of 2-D arrays, or one 3-D array
        One raw mosaic per illumination geometry (M frames of shape (H, W), H and W even), in
        the IMX250MZR layout of ``SUPERPIXEL``; uint8 or uint16 as the camera writes them
        (other integers in [0, 65535] are converted to uint16; float frames are scaled to uint16
        by polanalyser, by their maximum, which costs precision in dark pixels).  One 3-D array
        holds them along ``axis``; without it, along the axis (first or last) under which every
        frame has even sides, a shape that fits both being refused as ambiguous.
    demosaic : {"bilinear", "vng", "ea"}, default "bilinear"
        polanalyser's demosaicing (OpenCV's bilinear, variable number of gradients or
        edge-aware Bayer conversions); the output has the full resolution (H, W).
    dark : float or array_like, optional
        Black level subtracted from the four polarizer images before the Stokes fit: a number, a
        raw dark frame (H, W) or one per frame (M, H, W) (demosaiced the same way).
    saturation : float, optional
        Raw value at which the sensor saturates: every output pixel whose demosaicing footprint
        (3x3 raw pixels for bilinear, 5x5 otherwise) reaches it is NaN.  Default: the largest value
        of the frames' integer dtype (255, 65535; a 12-bit camera's 4095 must be given), no check
        for float frames.
    min_intensity : float, default 0
        Pixels with S0 <= this (after ``dark``) are NaN: no light, no DOP.
    dtype : {"float64", "float32"}, default "float64"
        Of the outputs.
    axis : {0, -1}, optional
        For one 3-D array of frames: the axis that holds the measurements, 0 for (M, H, W), -1 for
        (H, W, M) (the outputs' layout).

    Returns
    -------
    dop, s0 : numpy.ndarray, shape (H, W, M)
        The degree of linear polarization sqrt(S1^2 + S2^2) / S0 and the intensity S0 (in raw
        counts, after ``dark``).  NaN marks a missing measurement: saturated, at or below
        ``min_intensity``, or a DoLP above 1 (noise or misregistration at edges); S0 is NaN only
        where saturated.

    Raises
    ------
    ImportError
        Without polanalyser or OpenCV (``pip install 'pbrdf-cl[camera]'``).
    ValueError
        For frames of the wrong shape or dtype, or bad options, naming them.

    Examples
    --------
    >>> dop, s0 = dop_from_frames([raw0, raw1, raw2], saturation=4095)  # doctest: +SKIP
    >>> dop.shape  # doctest: +SKIP
    (2048, 2448, 3)
    """
    return stokes_from_frames(frames, demosaic=demosaic, dark=dark, saturation=saturation,
                              min_intensity=min_intensity, dtype=dtype, axis=axis)[:2]


def stokes_from_frames(frames, *, demosaic="bilinear", dark=None, saturation=None, min_intensity=0.0,
                       dtype="float64", axis=None):
    """DOP (DoLP), intensity S0 and normalised S1, S2 image stacks from raw DoFP polarization-camera
    frames (:func:`dop_from_frames` returns the first two).

    Parameters
    ----------
    frames : sequence of 2-D arrays, or one 3-D array
        One raw mosaic per illumination geometry (M frames of shape (H, W), H and W even), in
        the IMX250MZR layout of ``SUPERPIXEL``; uint8 or uint16 as the camera writes them
        (other integers in [0, 65535] are converted to uint16; float frames are scaled to uint16
        by polanalyser, by their maximum, which costs precision in dark pixels).  One 3-D array
        holds them along ``axis``; without it, along the axis (first or last) under which every
        frame has even sides, a shape that fits both being refused as ambiguous.
    demosaic : {"bilinear", "vng", "ea"}, default "bilinear"
        polanalyser's demosaicing (OpenCV's bilinear, variable number of gradients or
        edge-aware Bayer conversions); the output has the full resolution (H, W).
    dark : float or array_like, optional
        Black level subtracted from the four polarizer images before the Stokes fit: a number, a
        raw dark frame (H, W) or one per frame (M, H, W) (demosaiced the same way).
    saturation : float, optional
        Raw value at which the sensor saturates: every output pixel whose demosaicing footprint
        (3x3 raw pixels for bilinear, 5x5 otherwise) reaches it is NaN.  Default: the largest value
        of the frames' integer dtype (255, 65535; a 12-bit camera's 4095 must be given), no check
        for float frames.
    min_intensity : float, default 0
        Pixels with S0 <= this (after ``dark``) are NaN: no light, no DOP.
    dtype : {"float64", "float32"}, default "float64"
        Of the outputs.
    axis : {0, -1}, optional
        For one 3-D array of frames: the axis that holds the measurements, 0 for (M, H, W), -1 for
        (H, W, M) (the outputs' layout).

    Returns
    -------
    dop, s0, s1, s2 : numpy.ndarray, shape (H, W, M)
        The degree of linear polarization sqrt(S1^2 + S2^2) / S0, the intensity S0 (in raw
        counts, after ``dark``) and S1 / S0, S2 / S0 in the sensor's frame (polarizer angles
        from its x axis).  NaN marks a missing measurement: saturated, at or below
        ``min_intensity``, or a DoLP above 1 (noise or misregistration at edges), in dop, s1 and s2;
        S0 is NaN only where saturated.

    Raises
    ------
    ImportError
        Without polanalyser or OpenCV (``pip install 'pbrdf-cl[camera]'``).
    ValueError
        For frames of the wrong shape or dtype, or bad options, naming them.

    Examples
    --------
    >>> dop, s0, s1, s2 = stokes_from_frames([raw0, raw1, raw2], saturation=4095)  # doctest: +SKIP
    >>> s1.shape  # doctest: +SKIP
    (2048, 2448, 3)
    """
    if demosaic not in DEMOSAIC:
        raise ValueError(f"demosaic must be one of {sorted(DEMOSAIC)}, got {demosaic!r}")
    if dtype not in ("float64", "float32", np.float64, np.float32):
        raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
    if not np.isfinite(min_intensity):
        raise ValueError(f"min_intensity must be a finite number, got {min_intensity!r}")
    raws = _frames(frames, axis)
    pa = polanalyser()
    shape, m = raws[0].shape, len(raws)
    darks = _darks(pa, dark, shape, m, demosaic)
    if saturation is None and np.issubdtype(raws[0].dtype, np.integer):
        saturation = float(np.iinfo(raws[0].dtype).max)
    if saturation is not None and not np.isfinite(saturation):
        raise ValueError(f"saturation must be a finite number, got {saturation!r}")
    dop = np.empty(shape + (m,), dtype=dtype)
    s0 = np.empty(shape + (m,), dtype=dtype)
    s1, s2 = np.empty(shape + (m,), dtype=dtype), np.empty(shape + (m,), dtype=dtype)
    angles = np.radians(POLARIZER_ANGLES)
    for j, raw in enumerate(raws):
        images = _demosaic(pa, raw, demosaic)
        if darks is not None:
            images = images - darks[j if len(darks) > 1 else 0]
        stokes = pa.calcStokes(images, angles)                        # (H, W, 3)
        intensity = pa.cvtStokesToIntensity(stokes)
        with np.errstate(divide="ignore", invalid="ignore"):
            dolp = pa.cvtStokesToDoLP(stokes)
        bad = ~(intensity > min_intensity) | ~(dolp <= 1.0 + 1e-9)   # rounding above a DoLP of 1 is kept
        if saturation is not None:
            from scipy.ndimage import maximum_filter
            hot = maximum_filter(raw, size=_FOOTPRINT[demosaic], mode="nearest") >= saturation
            bad |= hot
            intensity = np.where(hot, np.nan, intensity)
        dop[..., j] = np.where(bad, np.nan, np.minimum(dolp, 1.0))
        s0[..., j] = intensity
        with np.errstate(divide="ignore", invalid="ignore"):
            for out, c in ((s1, 1), (s2, 2)):
                out[..., j] = np.where(bad, np.nan, stokes[..., c] / stokes[..., 0])
    return dop, s0, s1, s2


def _darks(pa, dark, shape, m, method):
    """``dark`` as demosaiced float64 images (1 or M, 4, H, W), a (1, 1, 1, 1) number, or None."""
    if dark is None:
        return None
    d = np.asarray(dark)
    if d.ndim == 0:
        if not np.isfinite(d):
            raise ValueError(f"dark must be a finite number or a raw dark frame, got {dark!r}")
        return np.full((1, 1, 1, 1), float(d))
    frames = [d] if d.ndim == 2 else list(d)
    if d.ndim not in (2, 3) or (d.ndim == 3 and len(frames) != m) or any(f.shape != shape for f in frames):
        raise ValueError(f"dark must be a number, a raw frame of shape {shape} or {m} of them, got shape {d.shape}")
    return np.stack([_demosaic(pa, f, method) for f in frames])


def _angle(name, value, shape):
    """A geometry array: (M,) shared, or broadcastable to (H, W, M); with its dims."""
    a = pointwise.check_values(name, value)
    if a.size == 1 and a.ndim <= 1:
        a = np.full(shape[-1:], float(a.flat[0]))
    if a.ndim == 1:
        if a.shape != shape[-1:]:
            raise ValueError(f"{name} must have one value per frame ({shape[-1]}) or broadcast to {shape}, "
                             f"got shape {a.shape}")
        return ("m",), a
    try:
        return ("y", "x", "m"), np.array(np.broadcast_to(a, shape))
    except ValueError:
        raise ValueError(f"{name} must have one value per frame ({shape[-1]}) or broadcast to {shape}, "
                         f"got shape {a.shape}") from None


def camera_dataset(frames, theta_i, theta_r, phi=180.0, *, dop_std=None, mask=None, irradiance=None,
                   demosaic="bilinear", dark=None, saturation=None, min_intensity=0.0, axis=None, incident=None,
                   roll=None, s_std=None):
    """The Dataset of a per-pixel inversion from raw DoFP frames, their geometry and the source's
    polarization state.

    Parameters
    ----------
    frames : sequence of 2-D arrays, or one 3-D array
        M raw mosaics, one per illumination geometry (:func:`dop_from_frames`).  Of one 3-D array
        the measurement axis is ``axis``, else the one (first or last) whose length matches the
        geometry's per-frame values and leaves frames of even sides; an ambiguous shape is refused.
    theta_i, theta_r, phi : float or array_like
        Degrees, as everywhere in pbrdf-cl (phi = phi_i - phi_r, 180 = the mirror plane): one
        value per frame, shape (M,), or per pixel, broadcastable to (H, W, M);
        :func:`pbrdf_cl.io.imagestack.angles_from_positions` computes them from the positions of
        the light, the camera and each pixel's surface point.
    dop_std : float or array_like, optional
        The DOP's standard deviation, broadcastable to (H, W, M) (the fit's weights).
    mask : array_like of bool, shape (H, W), optional
        True where a pixel is to be fitted.
    irradiance : float or array_like, optional
        The irradiance of each frame at the sample (e.g. source power cos(theta_i) / r^2, in any
        one unit), broadcastable to (H, W, M).  With it the dataset has ``s0`` = S0 / irradiance,
        proportional to the BRDF F00 for unpolarised light (what the fit's intensity column must
        be); without it only ``intensity`` (raw S0), which the fit does not read.
    demosaic, dark, saturation, min_intensity, axis
        As for :func:`dop_from_frames`.
    incident : array_like, shape (3,) or (M, 3), optional
        The source's normalised Stokes vector (s1, s2, s3) per frame, in the incoming beam's s/p
        frame (SPEC.md): (0, 1, 0) is linear polarization at 45 degrees from s towards p, (1, 0, 0)
        along s, (0, 0, 1) circular.  Given (even (0, 0, 0)), the dataset holds it as ``in_s1``,
        ``in_s2``, ``in_s3`` over the frames, and :func:`pbrdf_cl.fit_batch` fits ``s1`` and ``s2``
        by default; without it the light is unpolarised and the fit takes ``dop`` as before.
    roll : float or array_like, optional
        Degrees: the angle from the outgoing beam's s axis to the sensor's x axis (counted from s
        towards p), per frame (M,) or per pixel, broadcastable to (H, W, M): S1 and S2 are rotated by
        it from the sensor's frame into the beam's.  Default: none, the sensor's x axis taken as the
        beam's s axis (see the module's note on frames).
    s_std : float or array_like, optional
        The standard deviation of ``s1`` and ``s2`` (normalised), broadcastable to (H, W, M): their
        weights (``s1_std``, ``s2_std``).

    Returns
    -------
    xarray.Dataset
        Dims (y, x, m): ``dop``, ``s1``, ``s2`` (S1 / S0, S2 / S0; NaN where dop is) and
        ``intensity`` (y, x, m); ``theta_i``, ``theta_r``, ``phi`` with dims (m,) or (y, x, m) as
        given; ``dop_std``, ``s1_std`` and ``s2_std``, ``mask``, ``s0`` and ``in_s1``, ``in_s2``,
        ``in_s3`` (m,) where given; attrs naming the camera layout, the demosaicing, the frame of
        s1 and s2 (``stokes_frame``) and the count of missing measurements.

    Raises
    ------
    ImportError
        Without polanalyser or OpenCV (``pip install 'pbrdf-cl[camera]'``).
    ValueError
        For frames, angles, dop_std, s_std, mask, irradiance, incident or roll of the wrong shape
        or out of range (an incident state that is not a Stokes vector, one line).

    Examples
    --------
    >>> ds = camera_dataset(frames, theta_i=[30, 40, 50], theta_r=45, phi=180)  # doctest: +SKIP
    >>> ds.dop.dims  # doctest: +SKIP
    ('y', 'x', 'm')
    >>> ds = camera_dataset(frames, [30, 40, 50], 45, incident=(0, 1, 0))  # doctest: +SKIP
    >>> float(ds.in_s2[0]), ds.s1.dims  # doctest: +SKIP
    (1.0, ('y', 'x', 'm'))
    """
    import xarray as xr

    raws = _frames(frames, axis, _geometry_count(theta_i, theta_r, phi))
    shape = raws[0].shape + (len(raws),)
    geometry = {name: _angle(name, v, shape) for name, v in (("theta_i", theta_i), ("theta_r", theta_r), ("phi", phi))}
    extra = {}
    if dop_std is not None:
        std = np.asarray(dop_std, dtype=np.float64)
        if not (np.isfinite(std).all() and (std > 0).all()):
            bad = std[~(np.isfinite(std) & (std > 0))]
            raise ValueError(f"dop_std must be finite and > 0, got {float(bad.flat[0])!r}")
        extra["dop_std"] = _broadcast("dop_std", std, shape)
    if s_std is not None:
        std = np.asarray(s_std, dtype=np.float64)
        if not (np.isfinite(std).all() and (std > 0).all()):
            bad = std[~(np.isfinite(std) & (std > 0))]
            raise ValueError(f"s_std must be finite and > 0, got {float(bad.flat[0])!r}")
        extra["s1_std"] = extra["s2_std"] = _broadcast("s_std", std, shape)
    if incident is not None:
        inc = _incident(incident, shape[-1])
        for j, name in enumerate(("in_s1", "in_s2", "in_s3")):
            extra[name] = (("m",), inc[:, j], {"units": "1", "long_name": f"the source's normalised Stokes s{j + 1}"})
    if roll is not None:
        r = np.asarray(roll, dtype=np.float64)
        if not np.isfinite(r).all():
            raise ValueError(f"roll must be finite (degrees), got {float(r[~np.isfinite(r)].flat[0])!r}")
        _, roll_deg = _broadcast("roll", r, shape)
    if mask is not None:
        mk = np.asarray(mask)
        if mk.dtype != bool or mk.shape != shape[:2]:
            raise ValueError(f"mask must be a boolean array of shape {shape[:2]}, got {mk.dtype} of shape {mk.shape}")
        extra["mask"] = (("y", "x"), mk)
    if irradiance is not None:
        irr = np.asarray(irradiance, dtype=np.float64)
        if not (np.isfinite(irr).all() and (irr > 0).all()):
            raise ValueError("irradiance must be finite and > 0, got "
                             f"{float(irr[~(np.isfinite(irr) & (irr > 0))].flat[0])!r}")
        irr_dims, irr = _broadcast("irradiance", irr, shape)
    dop, s0, s1, s2 = stokes_from_frames(raws, demosaic=demosaic, dark=dark, saturation=saturation,
                                         min_intensity=min_intensity)
    frame = "the sensor's (polarizer angles from its x axis), taken as the outgoing beam's s/p frame"
    if roll is not None:  # S1 + i S2 of the beam's frame is the sensor's turned by 2 roll
        c2, s2r = np.cos(np.radians(2.0 * roll_deg)), np.sin(np.radians(2.0 * roll_deg))
        s1, s2 = s1 * c2 - s2 * s2r, s1 * s2r + s2 * c2
        frame = "the outgoing beam's s/p frame (the sensor's rotated by roll)"
    yxm = ("y", "x", "m")
    variables = {"dop": (yxm, dop, {"units": "1", "long_name": "degree of linear polarization (DoLP)"}),
                 "s1": (yxm, s1, {"units": "1", "long_name": f"S1 / S0 in {frame}"}),
                 "s2": (yxm, s2, {"units": "1", "long_name": f"S2 / S0 in {frame}"}),
                 "intensity": (yxm, s0, {"units": "raw counts", "long_name": "Stokes S0 (not read by the fit)"})}
    if irradiance is not None:
        variables["s0"] = (yxm, s0 / np.broadcast_to(irr, shape),
                           {"units": "counts per irradiance unit", "long_name": "S0 / irradiance, proportional to F00"})
    for name, (dims, values) in geometry.items():
        variables[name] = (dims, values, {"units": "degree"})
    variables.update(extra)
    missing = int(np.count_nonzero(np.isnan(dop)))
    attrs = {"source": "DoFP polarization camera (IMX250MZR layout: 90 45 / 135 0), via polanalyser",
             "demosaic": demosaic, "angles": "degrees; phi = phi_i - phi_r, 180 = in-plane (mirror) geometry",
             "stokes_frame": frame,
             "incident": "given (in_s1, in_s2, in_s3)" if incident is not None else "unpolarised",
             "missing": missing,
             "missing_means": "NaN dop: saturated, S0 <= min_intensity, or DoLP > 1"}
    return xr.Dataset(variables, attrs=attrs)


def _incident(incident, m):
    """The source's states as an (M, 3) array, or a one-line ValueError."""
    inc = np.asarray(incident, dtype=np.float64)
    if inc.shape == (3,):
        inc = np.broadcast_to(inc, (m, 3))
    if inc.shape != (m, 3):
        raise ValueError(f"incident must be the source's normalised Stokes vector (s1, s2, s3), shape (3,), or one "
                         f"per frame, shape ({m}, 3), got shape {np.shape(incident)}")
    if not np.isfinite(inc).all():
        raise ValueError(f"incident must be finite, got {inc[~np.isfinite(inc).all(axis=1)][0].tolist()}")
    norm2 = (inc * inc).sum(axis=1)
    if (norm2 > 1.0 + 1e-9).any():
        j = int(np.argmax(norm2 > 1.0 + 1e-9))
        raise ValueError(f"incident[{j}] = ({', '.join(f'{v:g}' for v in inc[j])}) is not a Stokes vector: "
                         f"s1^2 + s2^2 + s3^2 = {norm2[j]:.4g} > 1 (normalised by S0)")
    return np.array(inc)


def _geometry_count(*angles):
    """The number of measurements the geometry implies: the length of a 1-d angle array with more
    than one value, or the last axis of a per-pixel one; None where every angle is a scalar."""
    for a in angles:
        a = np.asarray(a)
        if a.ndim >= 1 and a.shape[-1] > 1:
            return int(a.shape[-1])
    return None


def _broadcast(name, a, shape):
    """(dims, values) of ``a`` broadcast against (H, W, M): 0-d kept as a scalar."""
    if a.ndim == 0:
        return (), float(a)
    try:
        return ("y", "x", "m"), np.array(np.broadcast_to(a, shape))
    except ValueError:
        raise ValueError(f"{name} must broadcast to {shape}, got shape {a.shape}") from None
