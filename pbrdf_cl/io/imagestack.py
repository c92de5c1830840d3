"""Synthetic polarization image stacks: a flat sample of two materials under a moving point light,
and (:func:`polarimetric_stack`) what a linear polarization camera sees of it under a polarized
source.

:func:`synthetic_stack` renders the DOP that a fixed camera sees of a flat, rectified sample
(pixel (y, x) images one patch of the plane z = 0) while a point source takes ``n_lights``
positions.  Each pixel sees its own geometry, computed from the 3-D positions by
:func:`angles_from_positions` (theta = angle to the surface normal, phi = azimuth of the light
direction minus azimuth of the view direction, in [0, 360): phi = 180 is the mirror plane, as in
SPEC.md).  The DOP comes from :func:`pbrdf_cl.dop`, the Stokes vectors from :func:`pbrdf_cl.stokes`,
on the float64 numpy reference; nothing here evaluates the model itself.

The parameter maps are known, so the stack tests a per-pixel inversion end to end: a metal (the
paper's 45# steel, n = 1.6, k = 2.139) around a disc of a dielectric-like coating, each with its
own kd (meaning kd/ks, ks = 1) and c, and a roughness (sigma) gradient from left to right.
"""
from __future__ import annotations

import numpy as np

from .. import sizes
from ..compute.pointwise import dop as _dop
from ..compute.pointwise import stokes as _stokes
from ..model import inputs
from . import files

#: The two materials of :func:`synthetic_stack`: name -> n, k, kd (= kd/ks with ks = 1), c.
MATERIALS = {
    "metal": dict(n=1.6, k=2.139, kd=0.15, c=-0.3),       # the paper's 45# steel at 435 nm
    "dielectric": dict(n=1.405, k=0.2289, kd=0.3, c=-0.6),  # the paper's black paint (Table 1), more diffuse
}
#: sigma at the left and right edges of :func:`synthetic_stack`'s image (linear in x).
SIGMA_RANGE = (0.15, 0.6)
#: No light or view direction of a synthetic stack lies this close to grazing (degrees).
MAX_ZENITH = 89.0
#: Points per call of :func:`pbrdf_cl.dop` (bounds the reference's temporaries to ~60 MB).
_CHUNK = 1 << 18


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angles_from_positions(surface, light, camera, normal=(0.0, 0.0, 1.0)):
    """Zenith angles and relative azimuth of a point light and a camera seen from surface points.

    Parameters
    ----------
    surface, light, camera : array_like, shape (..., 3)
        Positions (any one length unit) of the surface points, of the light source and of the
        camera's pinhole; they broadcast together (e.g. surface (y, x, 1, 3) against light (m, 3)).
    normal : array_like, shape (..., 3), default (0, 0, 1)
        The mean surface normal (need not be a unit vector).

    Returns
    -------
    theta_i, theta_r, phi : numpy.ndarray
        Degrees: the angles of the light and view directions to the normal, and the azimuth of the
        light direction minus that of the view direction (counter-clockwise about the normal), in
        [0, 360), broadcast to one shape.  A mirror configuration gives phi = 180 and
        theta_i = theta_r; where a direction is along the normal its azimuth is undefined and
        phi is 0.

    Examples
    --------
    >>> ti, tr, phi = angles_from_positions([0, 0, 0], [-1, 0, 1], [1, 0, 1])
    >>> print(round(float(ti), 9), round(float(tr), 9), round(float(phi), 9))
    45.0 45.0 180.0
    """
    surface, light, camera = (np.asarray(a, dtype=np.float64) for a in (surface, light, camera))
    nrm = _unit(np.asarray(normal, dtype=np.float64))
    for name, a in (("surface", surface), ("light", light), ("camera", camera), ("normal", nrm)):
        if a.shape[-1:] != (3,):
            raise ValueError(f"{name} must have a last axis of length 3 (x, y, z), got shape {a.shape}")
    wi, wr = _unit(light - surface), _unit(camera - surface)
    ci, cr = np.sum(wi * nrm, axis=-1), np.sum(wr * nrm, axis=-1)
    it, rt = wi - ci[..., None] * nrm, wr - cr[..., None] * nrm     # projections on the tangent plane
    # signed angle from the view's azimuth to the light's, counter-clockwise about the normal
    phi = np.degrees(np.arctan2(np.sum(np.cross(rt, it) * nrm, axis=-1), np.sum(rt * it, axis=-1)))
    theta_i = np.degrees(np.arctan2(np.linalg.norm(it, axis=-1), ci))
    theta_r = np.degrees(np.arctan2(np.linalg.norm(rt, axis=-1), cr))
    phi = np.mod(phi, 360.0)
    phi = np.where(phi == 360.0, 0.0, phi)   # np.mod(-1e-17, 360) rounds to 360
    return tuple(np.array(a) for a in np.broadcast_arrays(theta_i, theta_r, phi))


def _spherical(distance, theta, azimuth):
    """Cartesian points at ``distance`` from the origin, zenith ``theta`` and azimuth (degrees)."""
    t, a = np.radians(theta), np.radians(azimuth)
    return distance * np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=-1)


#: Relative azimuths (phi at the sample's centre, degrees) of the columns of :func:`light_positions`,
#: in the order they are used: the mirror plane first, then pairs either side of it.
LIGHT_AZIMUTHS = (180.0, 150.0, 210.0, 115.0, 245.0)


def _check_lights(n_lights):
    if isinstance(n_lights, bool) or not float(n_lights).is_integer() or int(n_lights) < 1:
        raise ValueError(f"n_lights must be an integer of at least 1, got {n_lights!r}")
    return int(n_lights)


def light_positions(n_lights=30, *, camera_theta=60.0, camera_azimuth=270.0, distance=400.0, zenith=(15.0, 80.0),
                    spread=(10.0, 15.0)):
    """The point-light positions of :func:`synthetic_stack`, on a sphere about the sample's centre.

    Two parts.  First ``n_lights // 5`` (at most 5) positions about the camera's mirror direction
    (zenith ``camera_theta``, relative azimuth 180): the mirror direction itself, then
    +-``spread[0]`` degrees in zenith and +-``spread[1]`` in azimuth, so that every pixel has a
    measurement within a few degrees of facet tilt of its own mirror direction (8 degrees with
    the defaults), which carries most of the information on n and k.  Then the rest on a grid of
    rows of zenith angles by columns of relative azimuths (``LIGHT_AZIMUTHS``: the mirror
    plane and pairs at 180 +- 30 and +- 65 degrees, the forward half where the specular lobe
    lies), the rows denser towards grazing (zenith ``lo + (hi - lo) sin(pi/2 t)``, t uniform in
    [0, 1]): grazing light separates c, the spread of facet angles sigma and kd.  The columns are
    ``round(sqrt(rest / 1.2))`` (at most 5), the rows enough for the rest; surplus grid positions
    are dropped from the outer columns of the lowest row.  This design was chosen over golden-angle
    spirals over the hemisphere (back-scattering lights see DOP near 0 and add little) and over
    the grid alone by the Fisher information of (n, k, sigma, kd, c) at the DOP noise 0.005.

    Parameters
    ----------
    n_lights : int, default 30
        How many positions (at least 1).
    camera_theta, camera_azimuth : float, default 60, 270
        Direction of the camera from the sample's centre (degrees); relative azimuths are counted
        from the camera's.
    distance : float, default 400
        Distance of the lights from the sample's centre (the unit of the sample's coordinates, mm).
    zenith : (float, float), default (15, 80)
        The lowest and highest zenith angles (degrees) of the grid's rows.
    spread : (float, float), default (10, 15)
        Offsets (degrees) in zenith and azimuth of the near-specular positions.

    Returns
    -------
    numpy.ndarray, shape (n_lights, 3)
        x, y, z of each position: the near-specular ones first, then the grid row by row from the
        lowest zenith.

    Examples
    --------
    >>> light_positions(8).shape
    (8, 3)
    """
    n_lights = _check_lights(n_lights)
    dz, da = spread
    near = [(camera_theta, 180.0), (camera_theta - dz, 180.0), (camera_theta + dz, 180.0),
            (camera_theta, 180.0 - da), (camera_theta, 180.0 + da)][:min(5, n_lights // 5)]
    rest = n_lights - len(near)
    n_az = max(1, min(len(LIGHT_AZIMUTHS), int(round(np.sqrt(rest / 1.2)))))
    n_rows = -(-rest // n_az)
    lo, hi = zenith
    rows = lo + (hi - lo) * np.sin(np.pi / 2 * np.linspace(0.0, 1.0, n_rows))
    grid = [(z, a) for z in rows for a in LIGHT_AZIMUTHS[:n_az]]
    surplus = len(grid) - rest
    grid = grid[:n_az - surplus] + grid[n_az:]
    return np.array([_spherical(distance, z, camera_azimuth + a) for z, a in near + grid])


def truth_maps(size=256):
    """The parameter maps of :func:`synthetic_stack` over (y, x).

    Parameters
    ----------
    size : int, default 256
        Pixels along each side.

    Returns
    -------
    dict
        ``material`` (int8: 0 metal, 1 dielectric; a disc of radius 0.3 * size about the centre is
        the dielectric) and float64 maps ``n``, ``k``, ``sigma``, ``kd`` (kd/ks), ``c``; sigma
        rises linearly in x over ``SIGMA_RANGE``.

    Examples
    --------
    >>> m = truth_maps(16)
    >>> sorted(m), m["n"].shape
    (['c', 'k', 'kd', 'material', 'n', 'sigma'], (16, 16))
    """
    size = _check_size(size)
    sizes.check_memory(MAPS_BYTES_PER_PIXEL * size * size, f"truth maps of {size} x {size} pixels",
                       "use a smaller size")
    centre = (np.arange(size) + 0.5) / size - 0.5
    yy, xx = np.meshgrid(centre, centre, indexing="ij")
    material = (np.hypot(xx, yy) < 0.3).astype(np.int8)
    maps = {"material": material}
    for name in MATERIALS["metal"]:
        values = np.array([MATERIALS["metal"][name], MATERIALS["dielectric"][name]])
        maps[name] = values[material]
    lo, hi = SIGMA_RANGE
    maps["sigma"] = np.broadcast_to(np.linspace(lo, hi, size), (size, size)).copy()   # first to last column
    return maps


#: Peak memory of :func:`synthetic_stack` per measurement (pixel x light): the geometry's 3-vector
#: temporaries (light directions, their tangent parts, cross products), the angles, the parameters
#: and the outputs, measured at 115-265 bytes with tracemalloc for 128-256 pixels and 8-30
#: lights, with the fixed part below; the estimate is above every measurement.
STACK_BYTES_PER_MEASUREMENT = 120
#: The fixed part of that peak: the reference's temporaries for one chunk of :data:`_CHUNK` points.
STACK_BYTES_FIXED = 80 << 20
#: Peak memory of :func:`truth_maps` per pixel (57 bytes measured: the maps and the disc's
#: coordinates), with a margin.
MAPS_BYTES_PER_PIXEL = 64


def stack_bytes(size, n_lights):
    """An upper estimate of the memory :func:`synthetic_stack` takes.

    Parameters
    ----------
    size : int
        Pixels along each side.
    n_lights : int
        Light positions M.

    Returns
    -------
    int
        Bytes: ``STACK_BYTES_PER_MEASUREMENT`` per pixel and light, plus ``STACK_BYTES_FIXED``.

    Examples
    --------
    >>> from pbrdf_cl.sizes import human
    >>> human(stack_bytes(256, 30)), human(stack_bytes(20000, 30))
    ('305 MiB', '1.31 TiB')
    """
    return STACK_BYTES_PER_MEASUREMENT * int(size) * int(size) * int(n_lights) + STACK_BYTES_FIXED


def _check_size(size):
    if isinstance(size, bool) or not float(size).is_integer() or int(size) < 2:
        raise ValueError(f"size must be an integer of at least 2 pixels, got {size!r}")
    return int(size)


def synthetic_stack(size=256, n_lights=30, noise=0.005, seed=0, *, sample_mm=100.0, camera_distance=300.0,
                    camera_theta=60.0, camera_azimuth=270.0, light_distance=400.0, lights=None, shadowing="paper"):
    """A synthetic DOP image stack of a flat two-material sample with known parameter maps.

    Parameters
    ----------
    size : int, default 256
        The image is ``size`` x ``size`` pixels, each imaging one square patch of a sample of side
        ``sample_mm`` centred at the origin of the plane z = 0 (the images are rectified to the
        sample plane; x to the right, y upwards, row 0 at the top).
    n_lights : int, default 30
        Positions M of the point light (:func:`light_positions`).
    noise : float, default 0.005
        Standard deviation of the Gaussian noise added to the DOP (then clipped to [0, 1]).
    seed : int, default 0
        Seed of the noise (numpy's ``default_rng``): the same seed gives the same stack.
    sample_mm, camera_distance, light_distance : float, default 100, 300, 400
        Side of the sample, distance of the camera's pinhole and of the lights from its centre (mm).
    camera_theta, camera_azimuth : float, default 60, 270
        Direction of the camera from the sample's centre (degrees): off-axis, so theta_r varies
        across the image (about 55..64 degrees with the defaults; theta_i spans about 6..81).
    lights : array_like, shape (M, 3), optional
        Light positions (mm) to use instead of :func:`light_positions` (``n_lights`` and
        ``light_distance`` are then ignored).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function of the model rendered.

    Returns
    -------
    xarray.Dataset
        Dims (y, x, m).  ``dop`` (y, x, m), ``theta_i``, ``theta_r``, ``phi`` (y, x, m, degrees),
        ``dop_std`` (a scalar, the noise std, broadcastable to ``dop``), the truth ``true_n``,
        ``true_k``, ``true_sigma``, ``true_kd`` (kd/ks, ks = 1), ``true_c`` and ``material``
        (y, x); coordinates ``x_mm``, ``y_mm`` (pixel centres), ``light_x``, ``light_y``,
        ``light_z`` (m); attrs describing the units, the geometry, the noise (``noise_std``,
        ``seed``, ``clipped``: how many values were clipped to [0, 1]) and the camera
        (``camera_mm``).

    Raises
    ------
    ValueError
        For a bad size, n_lights or noise, or a geometry with a light or view direction at
        ``MAX_ZENITH`` degrees or more; :class:`pbrdf_cl.TooLargeError` (a ValueError and a
        MemoryError) before any work when the stack cannot fit in memory (:func:`stack_bytes`).

    Examples
    --------
    >>> ds = synthetic_stack(16, n_lights=8)
    >>> ds.dop.dims, ds.dop.shape
    (('y', 'x', 'm'), (16, 16, 8))
    """
    import xarray as xr

    size = _check_size(size)
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite number >= 0, got {noise!r}")
    if lights is None:
        count = _check_lights(n_lights)
    else:
        lights = np.asarray(lights, dtype=np.float64)
        if lights.ndim != 2 or lights.shape[1] != 3 or not np.isfinite(lights).all():
            raise ValueError(f"lights must be finite positions of shape (M, 3), got shape {lights.shape}")
        count = len(lights)
    sizes.check_memory(stack_bytes(size, count), f"a synthetic stack of {size} x {size} pixels x {count} lights",
                       "use a smaller size or fewer lights")
    if lights is None:
        lights = light_positions(count, camera_theta=camera_theta, camera_azimuth=camera_azimuth,
                                 distance=light_distance)
    camera = _spherical(camera_distance, camera_theta, camera_azimuth)
    coords = ((np.arange(size) + 0.5) / size - 0.5) * sample_mm
    x_mm, y_mm = coords, coords[::-1]                                      # row 0 at the top
    surface = np.stack(np.broadcast_arrays(x_mm[None, :], y_mm[:, None], 0.0), axis=-1)   # (y, x, 3)
    ti, tr, phi = angles_from_positions(surface[:, :, None, :], lights[None, None], camera)
    worst = max(float(ti.max()), float(tr.max()))
    if worst >= MAX_ZENITH:
        raise ValueError(f"the geometry reaches a zenith angle of {worst:.3g} degrees (at most {MAX_ZENITH} "
                         "allowed): move the lights or the camera")
    truth = truth_maps(size)
    params = {name: np.broadcast_to(truth[name][:, :, None], ti.shape).ravel()
              for name in FIT_PARAMETERS}
    clean = np.empty(ti.size)
    flat = ti.ravel(), tr.ravel(), phi.ravel()
    for s in range(0, ti.size, _CHUNK):
        sl = slice(s, s + _CHUNK)
        clean[sl] = _dop(flat[0][sl], flat[1][sl], phi=flat[2][sl], ks=1.0, shadowing=shadowing, backend="numpy",
                         **{k: v[sl] for k, v in params.items()})
    clean = clean.reshape(ti.shape)
    rng = np.random.default_rng(seed)
    noisy = clean + rng.normal(0.0, noise, clean.shape) if noise > 0 else clean.copy()
    clipped = int(np.count_nonzero((noisy < 0) | (noisy > 1)))
    noisy = np.clip(noisy, 0.0, 1.0)

    yxm, yx = ("y", "x", "m"), ("y", "x")
    deg = {"units": "degree"}
    ds = xr.Dataset(
        {"dop": (yxm, noisy, {"units": "1", "long_name": "degree of polarization (unpolarized incidence)"}),
         "dop_std": ((), float(noise), {"units": "1", "long_name": "std of the DOP noise (every measurement)"}),
         "theta_i": (yxm, ti, {**deg, "long_name": "angle of the light direction to the normal"}),
         "theta_r": (yxm, tr, {**deg, "long_name": "angle of the view direction to the normal"}),
         "phi": (yxm, phi, {**deg, "long_name": "azimuth of light minus azimuth of view; 180 = mirror plane"}),
         "true_n": (yx, truth["n"], {"units": "1", "long_name": "true refractive index n"}),
         "true_k": (yx, truth["k"], {"units": "1", "long_name": "true extinction coefficient k"}),
         "true_sigma": (yx, truth["sigma"], {"units": "1", "long_name": "true per-axis slope std"}),
         "true_kd": (yx, truth["kd"], {"units": "1", "long_name": "true kd/ks (ks = 1)"}),
         "true_c": (yx, truth["c"], {"units": "1", "long_name": "true diffuse exponent c"}),
         "material": (yx, truth["material"], {"long_name": "0 = metal, 1 = dielectric"})},
        coords={"x_mm": ("x", x_mm, {"units": "mm"}), "y_mm": ("y", y_mm, {"units": "mm"}),
                "light_x": ("m", lights[:, 0], {"units": "mm"}), "light_y": ("m", lights[:, 1], {"units": "mm"}),
                "light_z": ("m", lights[:, 2], {"units": "mm"})},
        attrs={"title": "synthetic pBRDF DOP image stack (pbrdf_cl.io.imagestack.synthetic_stack)",
               "angles": "degrees; phi = phi_i - phi_r in [0, 360), 180 = in-plane (mirror) geometry",
               "geometry": (f"flat sample, side {sample_mm} mm, in the plane z = 0, normal +z, centred at the "
                            f"origin; rectified pixels (x right, y up, row 0 at the top); pinhole camera at "
                            f"{camera_distance} mm, zenith {camera_theta} deg, azimuth {camera_azimuth} deg; "
                            f"{len(lights)} point-light positions at {light_distance} mm from the centre"),
               "camera_mm": camera.tolist(),
               "model": f"six-parameter pBRDF, shadowing {shadowing!r}, ks = 1 (true_kd is kd/ks)",
               "materials": "; ".join(f"{m}: " + ", ".join(f"{k} = {v}" for k, v in p.items())
                                      for m, p in MATERIALS.items()),
               "sigma": f"linear in x from {SIGMA_RANGE[0]} (left) to {SIGMA_RANGE[1]} (right)",
               "noise": f"Gaussian DOP noise of std {noise}, numpy default_rng(seed {seed}), then clipped to [0, 1]",
               "noise_std": float(noise), "seed": int(seed), "clipped": clipped})
    return ds


#: The paper's geometry (SPEC: 45# steel at 435 nm): theta_i 30, 40, 50 by theta_r 20 .. 65 step 5, in plane.
PAPER_THETA_I = np.repeat([30.0, 40.0, 50.0], 10)
PAPER_THETA_R = np.tile(np.arange(20.0, 66.0, 5.0), 3)
#: Source states of :func:`polarimetric_stack`'s examples (normalised Stokes s1, s2, s3 in the incoming
#: beam's frame): linear at 45 degrees; linear at 0, 45, 90 degrees from s and right circular.
SOURCE_45 = ((0.0, 1.0, 0.0),)
SOURCE_FOUR = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def polarimetric_stack(size=16, states=SOURCE_45, noise=0.005, seed=0, *, theta_i=PAPER_THETA_I,
                       theta_r=PAPER_THETA_R, phi=180.0, shadowing="paper"):
    """A synthetic linear-polarization-camera stack under a polarized source, with known parameter maps.

    The sample of :func:`truth_maps` (two materials, a roughness gradient, ks = 1) seen at a shared
    geometry (every pixel the same angles, as a collimated source and a telecentric camera give) under
    each source state in turn: s1 = S1 / S0 and s2 = S2 / S0 of the reflected light (the psps frame of
    the outgoing beam) from :func:`pbrdf_cl.stokes`, plus Gaussian noise.

    Parameters
    ----------
    size : int, default 16
        Pixels along each side.
    states : sequence of (s1, s2, s3), default SOURCE_45
        The source's normalised Stokes vectors, each at every geometry (``SOURCE_FOUR``: linear at
        0, 45 and 90 degrees and circular).
    noise : float, default 0.005
        Standard deviation of the Gaussian noise added to s1 and s2 (their ``s1_std``, ``s2_std``).
    seed : int, default 0
        Seed of the noise (numpy's ``default_rng``).
    theta_i, theta_r, phi : array_like, default the paper's 30 in-plane geometries
        Degrees, one value per geometry (phi may be one number).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function of the model rendered.

    Returns
    -------
    xarray.Dataset
        Dims (y, x, m), M = geometries x states (the states vary fastest): ``s1``, ``s2`` (y, x, m),
        ``s1_std``, ``s2_std`` (scalars), ``theta_i``, ``theta_r``, ``phi``, ``in_s1``, ``in_s2``,
        ``in_s3`` (m), the truth ``true_n`` .. ``true_c`` and ``material`` (y, x), attrs saying so.

    Examples
    --------
    >>> ds = polarimetric_stack(4, states=SOURCE_FOUR)
    >>> ds.s1.shape, float(ds.in_s3[3])
    ((4, 4, 120), 1.0)
    """
    import xarray as xr

    size = _check_size(size)
    if not (np.isfinite(noise) and noise > 0):
        raise ValueError(f"noise must be a finite number > 0 (the stds of s1 and s2), got {noise!r}")
    inc = np.asarray(states, dtype=np.float64)
    if inc.ndim != 2 or inc.shape[1] != 3:
        raise ValueError(f"states must be (s1, s2, s3) vectors, shape (S, 3), got shape {inc.shape}")
    ti, tr = (np.asarray(a, dtype=np.float64).ravel() for a in (theta_i, theta_r))
    ph = np.broadcast_to(np.asarray(phi, dtype=np.float64), ti.shape)
    S = len(inc)
    geo = [np.repeat(a, S) for a in (ti, tr, ph)]
    inc = np.tile(inc, (ti.size, 1))
    truth = truth_maps(size)
    par = {name: truth[name][:, :, None] for name in FIT_PARAMETERS}
    st = _stokes(*geo, ks=1.0, shadowing=shadowing, backend="numpy", incident=inc, **par)
    rng = np.random.default_rng(seed)
    yxm, yx, m = ("y", "x", "m"), ("y", "x"), ("m",)
    data = {f"s{j}": (yxm, st[..., j] / st[..., 0] + rng.normal(0.0, noise, st.shape[:-1]),
                      {"units": "1", "long_name": f"S{j} / S0 of the reflected light (psps frame)"}) for j in (1, 2)}
    data.update({f"s{j}_std": ((), float(noise), {"units": "1"}) for j in (1, 2)})
    data.update({name: (m, a, {"units": "degree"}) for name, a in zip(("theta_i", "theta_r", "phi"), geo)})
    data.update({f"in_s{j + 1}": (m, inc[:, j], {"units": "1", "long_name": f"the source's normalised Stokes "
                                                                              f"s{j + 1}"}) for j in range(3)})
    data.update({f"true_{n}": (yx, truth[n], {"units": "1"}) for n in FIT_PARAMETERS})
    data["material"] = (yx, truth["material"], {"long_name": "0 = metal, 1 = dielectric"})
    states_text = "; ".join("(" + ", ".join(f"{v:g}" for v in row) + ")" for row in np.asarray(states, float))
    return xr.Dataset(data, attrs={
        "title": "synthetic linear-polarization-camera stack under a polarized source "
                 "(pbrdf_cl.io.imagestack.polarimetric_stack)",
        "angles": "degrees; phi = phi_i - phi_r, 180 = in-plane (mirror) geometry; shared by every pixel",
        "states": "the source's normalised Stokes vectors (in_s1, in_s2, in_s3), each at every geometry: "
                  + states_text,
        "model": f"six-parameter pBRDF, shadowing {shadowing!r}, ks = 1 (true_kd is kd/ks)",
        "materials": "; ".join(f"{k}: " + ", ".join(f"{a} = {b}" for a, b in p.items()) for k, p in MATERIALS.items()),
        "sigma": f"linear in x from {SIGMA_RANGE[0]} (left) to {SIGMA_RANGE[1]} (right)",
        "noise": f"Gaussian noise of std {noise} on s1 and s2, numpy default_rng(seed {seed})", "seed": int(seed)})


def save_stack(ds, path):
    """Write a stack to NetCDF (``.nc``, xarray's ``to_netcdf``) or to a numpy ``.npz``.

    Parameters
    ----------
    ds : xarray.Dataset
        A stack, e.g. from :func:`synthetic_stack`.
    path : str or path
        Ends in ``.nc`` or ``.npz``.  An ``.npz`` holds every variable and coordinate as an array
        of the same name, their dims as ``<name>.dims`` and the attributes as ``attrs.json``;
        :func:`load_stack` reads it back.

    Returns
    -------
    pathlib.Path
        The path written.

    Examples
    --------
    >>> save_stack(synthetic_stack(16, n_lights=8), "stack.npz")  # doctest: +SKIP
    """
    import json
    from pathlib import Path

    path = Path(path)
    if path.suffix == ".nc":
        ds.to_netcdf(path)
    elif path.suffix == ".npz":
        arrays = {}
        for name, var in {**ds.coords, **ds.data_vars}.items():
            arrays[name] = var.values
            arrays[f"{name}.dims"] = np.array(var.dims)
            arrays[f"{name}.attrs"] = np.array(json.dumps(dict(var.attrs)))
        arrays["attrs.json"] = np.array(json.dumps(dict(ds.attrs)))
        arrays["coords"] = np.array(list(ds.coords))
        np.savez_compressed(path, **arrays)
    else:
        raise ValueError(f"path must end in .nc or .npz, got {str(path)!r}")
    return path


def load_stack(path):
    """Read a stack written by :func:`save_stack` (``.nc`` or ``.npz``).

    Parameters
    ----------
    path : str or path
        Ends in ``.nc`` or ``.npz``.

    Returns
    -------
    xarray.Dataset
        The stack, with its dims, coordinates and attributes.

    Examples
    --------
    >>> ds = load_stack("stack.npz")  # doctest: +SKIP
    """
    import json
    from pathlib import Path

    import xarray as xr

    path = Path(path)
    if path.suffix == ".nc":
        with files.open_netcdf(path) as ds:
            return ds.load()
    if path.suffix != ".npz":
        raise ValueError(f"path must end in .nc or .npz, got {str(path)!r}")
    z = files.read_npz(path)
    try:
        names = [k for k in z if "." not in k and k != "coords"]
        coords = set(z["coords"].tolist())
        var = {k: (tuple(z[f"{k}.dims"].tolist()), z[k], json.loads(str(z[f"{k}.attrs"]))) for k in names}
        attrs = json.loads(str(z["attrs.json"]))
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a stack written by save_stack ({files.first_line(exc)})") from None
    return xr.Dataset({k: v for k, v in var.items() if k not in coords},
                      coords={k: v for k, v in var.items() if k in coords}, attrs=attrs)


#: The parameters a DOP-only fit determines (ks = 1), in the order of the truth maps.
FIT_PARAMETERS = inputs.FITTED
