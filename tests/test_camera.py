"""The polarization-camera path (pbrdf_cl.io.camera): raw DoFP mosaics in the IMX250MZR layout built
from known Stokes images with Malus' law, demosaiced by polanalyser, back to DoLP and S0."""
import sys

import numpy as np
import pytest

from pbrdf_cl.io import camera

H, W = 48, 64


def mosaic(s0, s1, s2, scale=1.0, dtype=np.uint16):
    """The raw frame a DoFP sensor records of the linear Stokes images (H, W): each pixel sees
    (S0 + S1 cos 2a + S2 sin 2a) / 2 through its polarizer a (camera.SUPERPIXEL)."""
    a = np.radians(np.array(camera.SUPERPIXEL))
    a = np.tile(a, (s0.shape[0] // 2, s0.shape[1] // 2))
    raw = 0.5 * (s0 + s1 * np.cos(2 * a) + s2 * np.sin(2 * a)) * scale
    return np.round(raw).astype(dtype) if np.issubdtype(dtype, np.integer) else raw.astype(dtype)


def stokes_fields():
    """Known Stokes images linear in x and y (bilinear demosaicing is exact for linear fields, so
    the interior is recovered to the quantisation of uint16): DoLP 0.002..0.44, AoLP -45..81 degrees."""
    y, x = np.mgrid[0:H, 0:W].astype(float)
    s0 = 20000 + 200 * x + 100 * y
    s1 = 2000 + 150 * x - 250 * y
    s2 = -1000 + 80 * x + 120 * y
    return s0, s1, s2, np.hypot(s1, s2) / s0


def interior(a, border=3):
    return a[border:-border, border:-border]


def test_missing_polanalyser_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "polanalyser", None)
    with pytest.raises(ImportError) as e:
        camera.dop_from_frames([np.zeros((4, 4), np.uint16)])
    msg = str(e.value)
    assert "pip install 'pbrdf-cl[camera]'" in msg and "\n" not in msg


def test_bad_frames_are_refused_before_polanalyser(monkeypatch):
    monkeypatch.setitem(sys.modules, "polanalyser", None)   # the checks need no polanalyser
    with pytest.raises(ValueError, match="even height and width"):
        camera.dop_from_frames([np.zeros((5, 4), np.uint16)])
    with pytest.raises(ValueError, match=r"frames\[1\] has shape"):
        camera.dop_from_frames([np.zeros((4, 4)), np.zeros((4, 6))])
    with pytest.raises(ValueError, match="wrap it in a list"):
        camera.dop_from_frames(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="demosaic must be one of"):
        camera.dop_from_frames([np.zeros((4, 4))], demosaic="nearest")
    # one 3-D array whose measurement axis both readings fit, (M, H, W) and (H, W, M): refused in one line
    for shape in ((16, 30, 16), (4, 48, 64)):
        with pytest.raises(ValueError) as err:
            camera.dop_from_frames(np.zeros(shape, np.uint16))
        text = str(err.value)
        assert f"shape {shape}" in text and "ambiguous" in text and "axis=" in text and "\n" not in text
    with pytest.raises(ValueError, match=r"fits neither .* with 5 measurements"):   # the geometry's count
        camera.camera_dataset(np.zeros((4, 48, 64), np.uint16), [30, 40, 50, 60, 70], 45)
    with pytest.raises(ValueError, match="ambiguous"):                               # 4 frames either way
        camera.camera_dataset(np.zeros((4, 48, 4), np.uint16), [30, 40, 50, 60], 45)
    with pytest.raises(ValueError, match="axis: only for frames given as one 3-D array"):
        camera.dop_from_frames([np.zeros((4, 4))], axis=0)


@pytest.fixture(scope="module")
def pa():
    pytest.importorskip("cv2", reason="polanalyser needs OpenCV (pip install 'pbrdf-cl[camera]')")
    return pytest.importorskip("polanalyser", reason="pip install 'pbrdf-cl[camera]'")


def test_superpixel_layout_is_polanalysers(pa):
    """The mosaic above, demosaiced and fitted by polanalyser itself, gives back S1 and S2 with
    their signs: camera.SUPERPIXEL is the layout polanalyser assumes (DoLP alone would not tell
    0 from 90 or 45 from 135 degrees)."""
    s0, s1, s2, _ = stokes_fields()
    images = pa.demosaicing(mosaic(s0, s1, s2), pa.COLOR_PolarMono)
    stokes = pa.calcStokes(np.asarray(images, float), np.radians(camera.POLARIZER_ANGLES))
    for got, want in zip(np.moveaxis(stokes, -1, 0), (s0, s1, s2)):
        assert np.max(np.abs(interior(got - want))) < 3.0   # counts, of ~20000-40000


def test_dolp_and_s0_from_a_stack_of_mosaics(pa):
    s0, s1, s2, dolp = stokes_fields()
    frames = [mosaic(s0 * f, s1 * f, s2 * f) for f in (1.0, 0.6)]
    frames.append(mosaic(s0, -s1, 0.3 * s2))                     # another DoLP, other signs
    dop, intensity = camera.dop_from_frames(frames)
    assert dop.shape == intensity.shape == (H, W, 3)
    want = [dolp, dolp, np.hypot(s1, 0.3 * s2) / s0]
    for j in range(3):
        assert np.max(np.abs(interior(dop[..., j] - want[j]))) < 1e-4
    assert np.max(np.abs(interior(intensity[..., 1] / (0.6 * s0) - 1))) < 1e-4
    assert np.isfinite(dop).all()


def test_one_3d_array_of_frames_by_its_measurement_axis(pa):
    """Frames stacked in one array, first or last: the reading under which every frame is whole
    super-pixels (or that matches the geometry's count, or axis=) gives the list's result."""
    s0, s1, s2, _ = stokes_fields()
    frames = [mosaic(s0 * f, s1 * f, s2 * f) for f in (1.0, 0.6, 0.3)]
    want = camera.dop_from_frames(frames)[0]
    for stacked in (np.stack(frames), np.stack(frames, axis=-1)):   # (3, H, W) and (H, W, 3)
        np.testing.assert_array_equal(camera.dop_from_frames(stacked)[0], want)
    four = frames + [frames[0]]
    want4 = camera.dop_from_frames(four)[0]
    np.testing.assert_array_equal(camera.dop_from_frames(np.stack(four), axis=0)[0], want4)
    np.testing.assert_array_equal(camera.dop_from_frames(np.stack(four, axis=-1), axis=-1)[0], want4)
    ds = camera.camera_dataset(np.stack(four, axis=-1), [30, 40, 50, 60], 45)   # (H, W, 4): 4 measurements
    assert ds.dop.shape == (H, W, 4)
    np.testing.assert_array_equal(ds.dop.values, want4)
    assert camera.camera_dataset(np.stack(four), [30, 40, 50, 60], 45).dop.shape == (H, W, 4)


def test_float_frames_and_constant_regions(pa):
    """Piecewise-constant Stokes (two regions): recovered away from the edge (demosaicing blurs
    it by a pixel or two); float frames go through polanalyser's scaling to uint16."""
    s0 = np.full((H, W), 1000.0)
    dolp = np.where(np.arange(W) < W // 2, 0.2, 0.7)[None, :] * np.ones((H, 1))
    s1, s2 = dolp * s0 * np.cos(1.0), dolp * s0 * np.sin(1.0)
    dop, _ = camera.dop_from_frames([mosaic(s0, s1, s2, dtype=np.float64)])
    left, right = dop[3:-3, 3:W // 2 - 3, 0], dop[3:-3, W // 2 + 3:-3, 0]
    assert np.max(np.abs(left - 0.2)) < 1e-3 and np.max(np.abs(right - 0.7)) < 1e-3
    edge = dop[3:-3, W // 2 - 1:W // 2 + 1, 0]
    assert np.max(np.abs(edge - 0.45)) < 0.26 and not np.allclose(edge, 0.2, atol=1e-2)  # blurred, in between


def test_saturation_dark_and_no_light_are_missing(pa):
    s0, s1, s2, dolp = stokes_fields()
    raw = mosaic(s0, s1, s2)
    raw[20, 30] = 4095 * 16                                      # one saturated raw pixel
    dop, intensity = camera.dop_from_frames([raw], saturation=4095 * 16)
    nan = np.isnan(dop[..., 0])
    assert nan[19:22, 29:32].all() and nan.sum() == 9 and np.isnan(intensity[19:22, 29:32, 0]).all()
    # a dark level of 1000 counts per polarizer image: S0 falls by 2000, DoLP rises accordingly
    dop, intensity = camera.dop_from_frames([mosaic(s0 + 2000, s1, s2)], dark=1000)
    assert np.max(np.abs(interior(dop[..., 0] - dolp))) < 1e-4
    assert np.max(np.abs(interior(intensity[..., 0] - s0))) < 3
    dop, _ = camera.dop_from_frames([np.zeros((H, W), np.uint16)])
    assert np.isnan(dop).all()                                   # no light: no DOP, not 0/0 warnings


def test_camera_dataset(pa):
    s0, s1, s2, dolp = stokes_fields()
    frames = [mosaic(s0 * f, s1 * f, s2 * f) for f in (1.0, 0.5, 0.25)]
    mask = np.zeros((H, W), bool)
    mask[5:-5, 5:-5] = True
    ds = camera.camera_dataset(frames, theta_i=[30, 40, 50], theta_r=45, phi=180, dop_std=0.01, mask=mask,
                               irradiance=[1.0, 0.5, 0.25])
    assert ds.dop.dims == ("y", "x", "m") and ds.dop.shape == (H, W, 3)
    assert ds.theta_i.dims == ("m",) and ds.theta_r.values.tolist() == [45.0] * 3
    assert ds.mask.dims == ("y", "x") and float(ds.dop_std) == 0.01
    np.testing.assert_allclose(interior(ds.s0.values[..., 2]), interior(s0), rtol=1e-3)
    np.testing.assert_allclose(interior(ds.dop.values[..., 1]), interior(dolp), atol=1e-4)
    per_pixel = np.broadcast_to(np.array([30.0, 40, 50]), (H, W, 3))
    assert camera.camera_dataset(frames, per_pixel, 45).theta_i.dims == ("y", "x", "m")
    with pytest.raises(ValueError, match=r"theta_i must be in \[0, 90\) degrees"):
        camera.camera_dataset(frames, [30, 40, 95], 45)
    with pytest.raises(ValueError, match="theta_r must have one value per frame"):
        camera.camera_dataset(frames, [30, 40, 50], [45, 45])
    with pytest.raises(ValueError, match="mask must be a boolean array"):
        camera.camera_dataset(frames, [30, 40, 50], 45, mask=np.ones((H, W)))
