"""pipeline.apply.panel on MicaSense's real RedEdge captures: panel found without manual help,
reflectance from the panel and from the DLS, NDVI of the flight capture; session.yaml's
panel polygon and the "no panel" error on a rendered image."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mscal_core.errors import FrameError, InputError
from mscal_core.factory import panel_stats, polygon_mask
from mscal_core.panel import polygon_iou
from pipeline.apply.panel import (
    capture_ndvi,
    dls_reflectance,
    panel_factors,
    panel_illumination,
    panel_reflectance,
    panel_region,
    reflect_area_polygon,
)
from pipeline.ingest.camera_meta import read_capture_meta
from pipeline.ingest.catalog import load_target
from pipeline.ingest.session import parse_panel, parse_panel_polygon
from pipeline.ingest.tiff import read_raw
from tests.micasense_data import MARKER_PANEL, PANEL_CORNERS, PANEL_RAW_DN, band_file, paint_marker

BANDS = range(1, 6)


@pytest.fixture(scope="module")
def panel_capture():
    metas = [read_capture_meta(band_file("0000", b)) for b in BANDS]
    return metas, [read_raw(m.path) for m in metas]


@pytest.fixture(scope="module")
def factors(panel_capture):
    metas, dns = panel_capture
    rho = load_target("micasense-rp02-1603036-sc").reflectance.at(np.array([m.wavelength_nm for m in metas]))
    return panel_factors(metas, dns, rho)


@pytest.fixture(scope="module")
def flight(factors):
    metas = [read_capture_meta(band_file("0001", b)) for b in BANDS]
    dns = [read_raw(m.path) for m in metas]
    panel = {m.band_name: panel_reflectance(m, d, f) for m, d, f in zip(metas, dns, factors)}
    dls = {m.band_name: dls_reflectance(m, d) for m, d in zip(metas, dns)}
    return metas, panel, dls


@pytest.mark.parametrize("band", BANDS)
def test_detected_panel_matches_published_corners_and_dn(panel_capture, factors, band: int) -> None:
    metas, dns = panel_capture
    region = factors[band - 1].region
    assert region.source == "detected"  # these files carry no ReflectArea
    iou = polygon_iou(dns[band - 1].shape, region.corners, PANEL_CORNERS[band - 1])
    assert iou >= 0.9  # measured 0.911-0.927 over the five bands
    mean = panel_stats(dns[band - 1], polygon_mask(dns[band - 1].shape, region.corners)).mean
    assert mean == pytest.approx(PANEL_RAW_DN[band - 1], rel=2e-3)  # measured within 0.12 %


@pytest.mark.parametrize("band", BANDS)
def test_panel_reflectance_of_the_panel_is_rho(panel_capture, factors, band: int) -> None:
    metas, dns = panel_capture
    f = factors[band - 1]
    refl = panel_reflectance(metas[band - 1], dns[band - 1], f)
    on_panel = refl[polygon_mask(refl.shape, f.region.corners)]
    assert float(on_panel.mean()) == pytest.approx(f.reflectance, rel=0.01)
    assert f.reflectance == pytest.approx((0.67, 0.69, 0.68, 0.61, 0.67)[band - 1])


def test_flight_ndvi_is_bimodal_vegetation_and_soil(flight) -> None:
    _, panel, _ = flight
    nd = capture_ndvi(panel["Red"], panel["NIR"])  # bands not co-registered
    nir = panel["NIR"]
    top = nir >= np.percentile(nir, 90)
    assert float(np.nanmedian(nd[top])) == pytest.approx(0.773, abs=0.03)
    assert float(np.nanmedian(nd)) == pytest.approx(0.621, abs=0.03)
    hist, edges = np.histogram(nd[np.isfinite(nd)], bins=20, range=(-0.2, 1.0))
    centres = 0.5 * (edges[:-1] + edges[1:])
    soil, veg = centres < 0.3, centres > 0.5
    soil_peak, veg_peak = hist[soil].max(), hist[veg].max()
    assert 0.0 < centres[soil][np.argmax(hist[soil])] < 0.25  # measured 0.13
    assert 0.6 < centres[veg][np.argmax(hist[veg])] < 0.85  # measured 0.73
    trough = hist[(centres > 0.3) & (centres < 0.5)].min()
    assert trough < 0.6 * soil_peak and trough < 0.3 * veg_peak


def test_panel_vs_dls_ratio_per_band(flight, factors) -> None:
    metas, panel, dls = flight
    ratios = [f.factor * m.irradiance / math.pi for f, m in zip(factors, metas)]
    assert all(math.isfinite(r) and r > 0 for r in ratios)
    # measured (Blue, Green, Red, NIR, Red edge): the raw DLS reading, no tilt correction
    assert ratios == pytest.approx([1.200, 0.939, 0.917, 0.750, 1.029], abs=0.005)
    for m, r in zip(metas, ratios):
        ok = np.isfinite(panel[m.band_name]) & (dls[m.band_name] > 0.01)
        assert float(np.median(panel[m.band_name][ok] / dls[m.band_name][ok])) == pytest.approx(r, rel=1e-4)


def test_dls_reflectance_needs_irradiance(panel_capture) -> None:
    metas, dns = panel_capture
    bad = dataclasses.replace(metas[0], irradiance=None)
    with pytest.raises(FrameError, match="no usable DLS irradiance") as exc:
        dls_reflectance(bad, dns[0])
    assert "IMG_0000_1.tif" in str(exc.value)


def test_reflect_area_wins_and_is_checked(panel_capture) -> None:
    metas, dns = panel_capture
    box = dataclasses.replace(metas[0], reflect_area=(646.0, 454.0, 162.0, 160.0))
    region = panel_region(box, dns[0])
    assert region.source == "xmp"
    assert region.corners.tolist() == [[646, 454], [808, 454], [808, 614], [646, 614]]
    quad = dataclasses.replace(metas[0], reflect_area=tuple(float(v) for v in np.ravel(PANEL_CORNERS[0])))
    assert reflect_area_polygon(quad).tolist() == [list(p) for p in PANEL_CORNERS[0]]
    with pytest.raises(FrameError, match="ReflectArea has 3 numbers"):
        reflect_area_polygon(dataclasses.replace(metas[0], reflect_area=(1.0, 2.0, 3.0)))
    with pytest.raises(FrameError, match="outside the 1280 x 960 image"):
        reflect_area_polygon(dataclasses.replace(metas[0], reflect_area=(1200.0, 900.0, 200.0, 200.0)))


def test_no_panel_names_the_file_and_session_polygon_is_the_fallback(panel_capture) -> None:
    metas, _ = panel_capture
    rng = np.random.default_rng(0)
    ground = np.clip(rng.normal(12000, 3000, metas[0].shape), 0, 65535).astype(np.uint16)
    with pytest.raises(FrameError, match="no reflectance panel found") as exc:
        panel_region(metas[0], ground)
    assert str(metas[0].path) in str(exc.value) and "session.yaml" in str(exc.value)
    region = panel_region(metas[0], ground, session_polygon=PANEL_CORNERS[0])
    assert region.source == "session"


def test_session_panel_polygon_parsing(tmp_path) -> None:
    path = tmp_path / "session.yaml"
    assert parse_panel_polygon({"polygon": [[646, 454], [808, 452], [809, 613]]}, path) == (
        (646.0, 454.0), (808.0, 452.0), (809.0, 613.0))
    for bad, msg in [
        ([[1, 2]], "must be a mapping"),
        ({"polygon": [[1, 2], [3, 4]]}, "at least 3"),
        ({"polygon": [[1, 2], [3, 4], [5]]}, r"panel\.polygon\[2\] must be \[x, y\]: pixel coordinates from 0 to 1e6, "
                                              r"got \[5\]"),
        ({"polygon": [[1, 2], [3, "x"], [5, 6]]}, r"panel\.polygon\[1\] must be \[x, y\].*got \[3, 'x'\]"),
        ({"polygon": [[-1, 2], [3, 4], [5, 9]]}, r"panel\.polygon\[0\] must be \[x, y\]: pixel coordinates from 0"),
        ({"polygon": [[0, 0], [5, 0], [5, 2e6]]}, r"panel\.polygon\[2\] must be .* to 1e6"),
        ({"polygon": [[0, 0], [5, 5], [10, 10]]}, "encloses no area"),
        ({"polygon": [[0, 0], [5, 0], [5, 5]], "corners": 4}, "unknown key"),
    ]:
        with pytest.raises(InputError, match=msg) as exc:
            parse_panel_polygon(bad, path)
        assert str(path) in str(exc.value)


@pytest.mark.parametrize("band", BANDS)
def test_panel_placed_by_a_marker_in_its_plane(panel_capture, band: int, tmp_path) -> None:
    metas, dns = panel_capture
    config = parse_panel(MARKER_PANEL, tmp_path / "session.yaml")
    dn = dns[band - 1].copy()
    assert panel_region(metas[band - 1], dn, config=config).source == "detected"  # no marker in view
    paint_marker(dn, band)
    region = panel_region(metas[band - 1], dn, config=config)
    assert region.source == "marker"
    iou = polygon_iou(dn.shape, region.corners, PANEL_CORNERS[band - 1])
    assert iou >= 0.85, iou  # the panel is tilted by ~0.7 degrees, the configured rectangle is not


def test_session_panel_marker_parsing(tmp_path) -> None:
    path = tmp_path / "session.yaml"
    cfg = parse_panel({**MARKER_PANEL, "polygon": [[0, 0], [5, 0], [5, 5]]}, path)
    assert cfg.marker is not None and cfg.marker.offset_m == (0.19, 0.0) and cfg.marker.panel_size_m == (0.215, 0.215)
    assert cfg.polygon == ((0.0, 0.0), (5.0, 0.0), (5.0, 5.0))
    mk = MARKER_PANEL["marker"]
    for bad, msg in [
        ({}, "needs a polygon or a marker"),
        ({"marker": mk}, "needs the panel's size_m"),
        ({**MARKER_PANEL, "offset_m": [0.05, 0.0]}, "covers the marker"),
        ({**MARKER_PANEL, "marker": {**mk, "dictionary": "DICT_9X9_1"}}, "not an OpenCV ArUco/AprilTag dictionary"),
        ({**MARKER_PANEL, "marker": {**mk, "id": -1}}, "non-negative integer"),
        ({"polygon": [[0, 0], [5, 0], [5, 5]], "size_m": 0.2}, "go with panel.marker"),
        ({**MARKER_PANEL, "rotation": 3}, "unknown key"),
    ]:
        with pytest.raises(InputError, match=msg) as exc:
            parse_panel(bad, path)
        assert str(path) in str(exc.value)


def test_light_on_the_panel_split_into_colour_and_brightness(panel_capture, factors) -> None:
    metas, dns = panel_capture
    fit = panel_illumination(metas, dns, factors)
    assert fit.converged and fit.residual_rms == pytest.approx(0.0135, abs=0.003)  # pixel noise
    # S rho is the median-lit spot's radiance: within 0.2 % of each band's mean panel radiance
    assert fit.spectral_factor * [f.reflectance for f in factors] == pytest.approx(
        [f.radiance for f in factors], rel=2e-3)
    b = fit.brightness.reshape(32, 32)
    lo, hi = np.nanpercentile(b, [5, 95])
    assert (lo, hi) == (pytest.approx(0.975, abs=0.005), pytest.approx(1.022, abs=0.005))
    cols = np.nanmean(b, axis=0)  # measured: about 2 % darker on the panel's left edge
    assert cols[:4].mean() < cols[12:20].mean() - 0.01


def test_one_panel_region_for_all_bands(panel_capture, tmp_path) -> None:
    """Band 1 carries the camera's small ReflectArea in one corner of the panel, the
    other bands none. Each band used to look at its own spot (band 1 that corner, the others the
    0.75 inset of their detection); now the corner is carried into every band through its own
    detection of the same square: the same panel coordinates in all five bands."""
    from mscal_core.panel import detect_panel, to_panel_coords
    from tests.camera_files import add_camera_element, rewrite, seq

    metas, dns = panel_capture
    c = np.array(PANEL_CORNERS[0], dtype=float)  # BR, BL, TL, TR of band 1
    small = np.round(c[2] + 0.1 * (c[0] - c[2])) + np.array([[40, 40], [0, 40], [0, 0], [40, 0]])  # 40 px near TL
    text = ",".join(f"{x:.0f},{y:.0f}" for x, y in small)
    path = rewrite(band_file("0000", 1), tmp_path / "IMG_0000_1.tif",
                   lambda x: add_camera_element(x, f"<Camera:ReflectArea>{seq(text)}</Camera:ReflectArea>"))
    metas1 = [read_capture_meta(path), *metas[1:]]
    rho = load_target("micasense-rp02-1603036-sc").reflectance.at(np.array([m.wavelength_nm for m in metas]))
    bands = panel_factors(metas1, dns, rho)
    assert [b.region.source for b in bands] == ["xmp:Blue"] * 5
    uv = [to_panel_coords(detect_panel(dn).outline, b.region.corners) for dn, b in zip(dns, bands)]
    for b in range(1, 5):
        np.testing.assert_allclose(uv[b], uv[0], atol=1e-6)
    assert uv[0].min() > 0.05 and uv[0].max() < 0.45  # the corner square, not the centred inset
    np.testing.assert_allclose(bands[0].region.corners, small, atol=1e-3)  # band 1 keeps the camera's area
