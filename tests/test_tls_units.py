"""The units a LAS/LAZ declares (GeoKeys 3076/4099 or a WKT record): metres used as they are,
international and US survey feet converted and said, any other unit refused naming it; E57's
coordinate metadata reported. The files are written by laspy and pye57 themselves (the writers), not
by our reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.core.errors import InputError
from depthstation.core.run_warnings import collecting

laspy = pytest.importorskip("laspy")
from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr  # noqa: E402

from depthstation.evaluate.scan.reference import load_reference  # noqa: E402

US_FOOT_M = 1200 / 3937
POINTS = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.5, -2.25, 0.5]])


def write_las(path: Path, pts: np.ndarray = POINTS, geokeys: dict[int, int] | None = None,
              wkt: str | None = None) -> Path:
    """A LAS (or LAZ by its suffix) through laspy, with a GeoKeyDirectory or a WKT record."""
    header = laspy.LasHeader(point_format=6 if wkt else 3, version="1.4" if wkt else "1.2")
    header.offsets = np.zeros(3)
    header.scales = np.full(3, 2.0**-10)
    if geokeys:
        vlr = GeoKeyDirectoryVlr()
        vlr.geo_keys_header.number_of_keys = len(geokeys)
        vlr.geo_keys = [GeoKeyEntryStruct(k, 0, 1, v) for k, v in geokeys.items()]
        header.vlrs.append(vlr)
    if wkt:
        header.vlrs.append(WktCoordinateSystemVlr(wkt))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))
    return path


def _read(path: Path) -> tuple[np.ndarray, list[str]]:
    with collecting() as found:
        _, cloud = load_reference(path)
    return np.asarray(cloud.points), [w.line() for w in found]


def test_metres_are_used_as_they_are(tmp_path: Path) -> None:
    pts, said = _read(write_las(tmp_path / "m.las", geokeys={1024: 1, 3072: 32632, 3076: 9001, 4099: 9001}))
    np.testing.assert_array_equal(pts, POINTS)  # the stored values, exactly (no multiplication by 1)
    assert said == []


def test_no_declared_unit_is_taken_as_metres_without_a_word(tmp_path: Path) -> None:
    pts, said = _read(write_las(tmp_path / "local.laz"))  # a scanner's own frame: no CRS at all
    np.testing.assert_array_equal(pts, POINTS)
    assert said == []


@pytest.mark.parametrize(("code", "metres", "name"), [(9002, 0.3048, "international foot"),
                                                      (9003, US_FOOT_M, "US survey foot")])
def test_feet_are_converted_and_said(tmp_path: Path, code: int, metres: float, name: str) -> None:
    path = write_las(tmp_path / "ft.laz", geokeys={1024: 1, 3076: code})
    pts, said = _read(path)
    # the stored values are multiples of 2^-10 ft: the conversion is exact to float64 rounding
    np.testing.assert_allclose(pts, POINTS * metres, rtol=1e-15, atol=0)
    assert len(said) == 1 and name in said[0] and "converted to metres" in said[0] and "3076" in said[0]
    assert str(path) in said[0]


def test_horizontal_feet_with_vertical_metres(tmp_path: Path) -> None:
    pts, said = _read(write_las(tmp_path / "mixed.las", geokeys={1024: 1, 3076: 9003, 4099: 9001}))
    np.testing.assert_allclose(pts[:, :2], POINTS[:, :2] * US_FOOT_M, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(pts[:, 2], POINTS[:, 2])
    assert "heights in metre" in said[0]


def test_wkt_in_us_survey_feet(tmp_path: Path) -> None:
    wkt = ('PROJCS["NAD83 / New York Long Island (ftUS)",GEOGCS["NAD83",DATUM["North_American_Datum_1983",'
           'SPHEROID["GRS 1980",6378137,298.257222101]],UNIT["degree",0.0174532925199433]],'
           'PROJECTION["Lambert_Conformal_Conic_2SP"],UNIT["US survey foot",0.304800609601219]]')
    pts, said = _read(write_las(tmp_path / "wkt.las", wkt=wkt))
    np.testing.assert_allclose(pts, POINTS * US_FOOT_M, rtol=1e-12, atol=0)
    assert "US survey foot (WKT)" in said[0]


@pytest.mark.parametrize(("keys", "wkt", "words"), [
    ({1024: 1, 3076: 9005}, None, ("ProjLinearUnitsGeoKey (3076)", "9005", "Clarke's foot")),
    ({1024: 1, 3076: 9001, 4099: 9036}, None, ("VerticalUnitsGeoKey (4099)", "kilometre")),
    ({1024: 2}, None, ("GTModelTypeGeoKey", "degrees")),
    (None, 'PROJCS["x",GEOGCS["g",UNIT["degree",0.0174532925199433]],'
           'UNIT["Gold Coast foot",0.3047997101815]]',
     ("WKT", "Gold Coast foot")),
    (None, 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
           'UNIT["degree",0.0174532925199433]]', ("WKT", "degrees")),
])
def test_other_units_are_refused_naming_them(tmp_path: Path, keys: dict[int, int] | None, wkt: str | None,
                                             words: tuple[str, ...]) -> None:
    path = write_las(tmp_path / "odd.las", geokeys=keys, wkt=wkt)
    with pytest.raises(InputError) as err:
        load_reference(path)
    assert err.value.path == path
    for w in words:
        assert w in err.value.problem, (w, err.value.problem)


def _e57(path: Path) -> Path:
    import pye57

    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw({"cartesianX": POINTS[:, 0], "cartesianY": POINTS[:, 1], "cartesianZ": POINTS[:, 2]})
    e57.close()
    return path


def test_e57_coordinate_metadata_is_reported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pye57 = pytest.importorskip("pye57")
    import uuid

    from pye57 import libe57

    from depthstation.evaluate.scan.tls import read_e57

    cloud = read_e57(_e57(tmp_path / "plain.e57"))
    np.testing.assert_allclose(cloud.xyz, POINTS, atol=1e-6)
    assert cloud.coordinates["unit"].startswith("metre")
    assert cloud.coordinates["coordinateMetadata"] is None  # said: the writer named no CRS
    assert cloud.coordinates["scans"] == 1
    crs = 'PROJCS["ETRS89 / UTM zone 32N",UNIT["metre",1]]'

    def header_with_crs(self: object) -> None:
        """pye57's own default header, with a coordinate system named."""
        imf = self.image_file  # type: ignore[attr-defined]
        root = self.root  # type: ignore[attr-defined]
        imf.extensionsAdd("", libe57.E57_V1_0_URI)
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
        root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
        root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
        root.set("coordinateMetadata", libe57.StringNode(imf, crs))
        root.set("data3D", libe57.VectorNode(imf, True))
        root.set("images2D", libe57.VectorNode(imf, True))

    monkeypatch.setattr(pye57.E57, "write_default_header", header_with_crs)
    cloud = read_e57(_e57(tmp_path / "utm.e57"))
    assert cloud.coordinates["coordinateMetadata"] == crs


def test_the_mesh_of_a_cloud_in_feet_is_in_metres_and_the_summary_says_so(tmp_path: Path) -> None:
    """Through reference_mesh (what the study calls): the mesh is made from metres, its info (the
    summary's reference_mesh) carries the units, and the warning comes again from the cached mesh."""
    from depthstation.evaluate.scan.reference import PoissonParams, reference_mesh

    rng = np.random.default_rng(4)
    d = rng.normal(size=(6000, 3))
    sphere_ft = 2.0 / US_FOOT_M * d / np.linalg.norm(d, axis=1, keepdims=True)  # radius 2 m, in US feet
    path = write_las(tmp_path / "ball.laz", sphere_ft, geokeys={1024: 1, 3076: 9003, 4099: 9003})
    for cached in (False, True):
        with collecting() as found:
            mesh, _, info = reference_mesh(path, tmp_path / "cache", PoissonParams(depth=5),
                                           viewpoints=np.zeros((1, 3)))
        assert info["cached"] is cached
        assert info["coordinates"]["horizontal_unit"] == "US survey foot"
        assert info["coordinates"]["converted_to_metres"] is True
        radius = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
        assert abs(float(np.median(radius)) - 2.0) < 0.05  # metres, not 6.56 (feet read as metres)
        assert [w.code for w in found] .count("reference-units") == 1
