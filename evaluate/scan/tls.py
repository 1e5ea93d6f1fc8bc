"""TLS point clouds as surveyors deliver them: LAS/LAZ (laspy) and E57 (pye57), read in float64
metres with what the file says about its coordinates.

Why the units matter: a LAS in US survey feet read as metres scales the whole reference by 3.28 and
every figure of the study with it. LAS records its linear unit in GeoKeys (ProjLinearUnitsGeoKey
3076, VerticalUnitsGeoKey 4099) or in a WKT record; metres are used as they are, international and US
survey feet converted (and said), any other unit refused. E57 stores metres by its standard; its
coordinate metadata (the CRS as text) is reported. A broken file (empty, cut short, its writer stopped)
is one line naming it, never an internal error.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import InputError

TLS_EXTRA = "pip install -e '.[tls]'"
Scans = list[tuple[int, int, np.ndarray]]  # (first point, end, scanner origin) per TLS station

PROJ_LINEAR_UNITS = 3076   # GeoKey: the projected CRS's linear unit (EPSG unit code)
VERTICAL_UNITS = 4099      # GeoKey: the vertical unit
GEOG_LINEAR_UNITS = 2052   # GeoKey: a geocentric CRS's linear unit
MODEL_TYPE = 1024          # GeoKey: 1 projected, 2 geographic (degrees), 3 geocentric
PROJECTED_CS = 3072        # GeoKey: the projected CRS's EPSG code
GEO_KEY_NAMES = {PROJ_LINEAR_UNITS: "ProjLinearUnitsGeoKey", VERTICAL_UNITS: "VerticalUnitsGeoKey",
                 GEOG_LINEAR_UNITS: "GeogLinearUnitsGeoKey"}
# EPSG unit codes: the ones understood (metres per unit) and names for the ones refused
UNITS_M = {9001: ("metre", 1.0), 9002: ("international foot", 0.3048), 9003: ("US survey foot", 1200 / 3937)}
OTHER_UNITS = {9004: "modified American foot", 9005: "Clarke's foot", 9006: "Indian foot", 9014: "fathom",
               9030: "nautical mile", 9031: "German legal metre", 9033: "US survey chain",
               9034: "US survey link", 9035: "US survey mile", 9036: "kilometre", 9037: "Clarke's yard",
               9038: "Clarke's chain", 9039: "Clarke's link", 9093: "statute mile", 32767: "user-defined"}
_WKT_UNIT = re.compile(r'(?<![A-Z_])(?:LENGTHUNIT|UNIT)\[\s*"([^"]*)"\s*,\s*([0-9.eE+-]+)')
_WKT_VERTICAL = re.compile(r"(?<![A-Z_])(?:VERT_CS|VERTCRS|VERTICALCRS)\[")
_ANGULAR = ("degree", "radian", "grad", "gon", "arc")


@dataclass
class TlsCloud:
    xyz: np.ndarray                      # (n, 3) float64, metres
    rgb: np.ndarray | None = None
    intensity: np.ndarray | None = None
    scans: Scans | None = None           # E57 stations with a pose
    coordinates: dict[str, Any] = field(default_factory=dict)  # what the file says (summary)


@dataclass(frozen=True)
class Unit:
    name: str
    metres: float
    source: str   # where the file says it (a GeoKey, the WKT)


def _metres_unit(path: Path, name: str, metres: float, source: str) -> Unit:
    """A unit by its size: metres, international or US survey feet, else refused naming it."""
    for known, size in UNITS_M.values():
        if abs(metres - size) <= 1e-9 * size:
            return Unit(known, size, source)
    raise InputError(path, f"{source}: the coordinates are in {name!r} ({metres:g} m): only metres, "
                           "international feet and US survey feet are understood; convert the cloud to "
                           "metres")


def _epsg_unit(path: Path, code: int, key: int) -> Unit:
    source = f"GeoKey {GEO_KEY_NAMES.get(key, key)} ({key})"
    if code in UNITS_M:
        name, size = UNITS_M[code]
        return Unit(name, size, f"{source} = {code}")
    raise InputError(path, f"{source}: the coordinates are in EPSG unit {code} "
                           f"({OTHER_UNITS.get(code, 'not a linear unit known here')}): only metres (9001), "
                           "international feet (9002) and US survey feet (9003) are understood; convert the "
                           "cloud to metres")


def wkt_units(path: Path, wkt: str) -> tuple[Unit | None, Unit | None]:
    """(horizontal, vertical) linear units of a WKT (1 or 2); a geographic CRS (degrees) refused."""
    split = _WKT_VERTICAL.search(wkt)
    head, tail = (wkt[:split.start()], wkt[split.start():]) if split else (wkt, "")

    def linear(text: str) -> tuple[str, float] | None:
        found = [(n, float(f)) for n, f in _WKT_UNIT.findall(text)
                 if not any(a in n.lower() for a in _ANGULAR)]
        return found[-1] if found else None

    horizontal = linear(head)
    if horizontal is None and head.strip() and re.match(r"\s*(GEOGCS|GEOGCRS|GEOGRAPHICCRS)\[", head):
        raise InputError(path, "WKT: a geographic CRS (coordinates in degrees): project the cloud to metres")
    h = None if horizontal is None else _metres_unit(path, horizontal[0], horizontal[1], "WKT")
    vertical = linear(tail)
    v = None if vertical is None else _metres_unit(path, vertical[0], vertical[1], "WKT (vertical CRS)")
    return h, v


def geokey_units(path: Path, keys: dict[int, int]) -> tuple[Unit | None, Unit | None, int | None]:
    """(horizontal, vertical, projected CRS code) from GeoKeys; a geographic model (degrees) refused."""
    if keys.get(MODEL_TYPE) == 2:
        raise InputError(path, f"GeoKey GTModelTypeGeoKey ({MODEL_TYPE}) = 2: a geographic CRS "
                               "(coordinates in degrees): project the cloud to metres")
    h = None
    for key in (PROJ_LINEAR_UNITS, GEOG_LINEAR_UNITS):
        if key in keys:
            h = _epsg_unit(path, keys[key], key)
            break
    v = _epsg_unit(path, keys[VERTICAL_UNITS], VERTICAL_UNITS) if VERTICAL_UNITS in keys else None
    return h, v, keys.get(PROJECTED_CS)


def las_units(path: Path, vlrs: Any) -> tuple[Unit, Unit, dict[str, Any]]:
    """The horizontal and vertical units a LAS declares, and the summary's words on them."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    wkt = next((v.string for v in vlrs if isinstance(v, WktCoordinateSystemVlr) and v.string), None)
    keys: dict[int, int] = {}
    for v in vlrs:
        if isinstance(v, GeoKeyDirectoryVlr):  # values stored in the key itself (location 0) only
            keys.update({int(k.id): int(k.value_offset) for k in v.geo_keys if int(k.tiff_tag_location) == 0})
    info: dict[str, Any] = {}
    crs = None
    if wkt is not None:
        h, v = wkt_units(path, wkt)
        info["wkt"] = wkt
    else:
        h, v, crs = geokey_units(path, keys)
        if keys:
            info["geokeys"] = {str(k): val for k, val in sorted(keys.items())}
    if crs is not None:
        info["epsg"] = crs
    metre = Unit("metre", 1.0, "")
    if h is None:
        h = Unit("metre", 1.0, "no linear unit declared: taken as metres")
        if crs is not None and crs != 32767:
            info["unit_note"] = (f"EPSG:{crs} is named but not its linear unit (ProjLinearUnitsGeoKey): "
                                 "taken as metres")
    if v is None:
        v = Unit(h.name, h.metres, "no vertical unit declared: taken as the horizontal one")
    info.update({"horizontal_unit": h.name, "horizontal_unit_from": h.source, "vertical_unit": v.name,
                 "vertical_unit_from": v.source,
                 "converted_to_metres": h.metres != metre.metres or v.metres != metre.metres})
    return h, v, info


def _laz_backend_missing(laspy: Any) -> bool:
    try:
        return not any(backend.is_available() for backend in laspy.LazBackend)
    except Exception:
        return False


def _laspy(path: Path) -> Any:
    try:
        import laspy
    except ImportError as exc:
        raise InputError(path, f"LAS/LAZ needs the optional package 'laspy' ({TLS_EXTRA}), "
                               "or convert the cloud to PLY") from exc
    return laspy


def check_las(path: Path) -> tuple[Any, int, bool, Unit, Unit, dict[str, Any]]:
    """A LAS/LAZ's header checked without reading its points: (header, points, compressed, units,
    the summary's words). No points, a cut uncompressed file or a unit not understood: refused."""
    laspy = _laspy(path)
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
    except Exception as exc:
        raise InputError(path, f"not a readable LAS/LAZ file ({type(exc).__name__}: "
                               f"{_first_line(exc)})") from exc
    n = int(header.point_count)
    if n == 0:
        raise InputError(path, "holds no points (its header says 0): nothing to mesh a reference from")
    compressed = path.suffix.lower() == ".laz" or header.point_format.id >= 128 or bool(
        getattr(header, "are_points_compressed", False))
    size = path.stat().st_size
    needed = int(header.offset_to_point_data) + n * int(header.point_format.size)
    if not compressed and size < needed:
        raise InputError(path, f"cut short: its header announces {n} points ({needed} bytes with the "
                               f"header), the file holds {size} bytes")
    h, v, info = las_units(path, header.vlrs)
    return header, n, compressed, h, v, info


def read_las(path: Path) -> TlsCloud:
    """A LAS/LAZ in float64 metres (its declared unit converted), intensity and RGB."""
    laspy = _laspy(path)
    header, n, compressed, h, v, info = check_las(path)
    try:
        las = laspy.read(str(path))
    except Exception as exc:
        text = _first_line(exc)
        if compressed and _laz_backend_missing(laspy):
            raise InputError(path, f"cannot read ({type(exc).__name__}: {text}); no LAZ backend is "
                                   f"installed: {TLS_EXTRA} installs one (lazrs)") from exc
        if re.search(r"fill whole buffer|unexpected ?eof|buffer size must be", text, re.IGNORECASE):
            raise InputError(path, f"cut short: its header announces {n} points, the compressed data end "
                                   f"before them ({type(exc).__name__}: {text})") from exc
        raise InputError(path, f"cannot read ({type(exc).__name__}: {text})") from exc
    xyz = np.asarray(las.xyz, dtype=np.float64)
    if len(xyz) < n:
        raise InputError(path, f"cut short: its header announces {n} points, {len(xyz)} read")
    if h.metres != 1.0:
        xyz[:, :2] *= h.metres
    if v.metres != 1.0:
        xyz[:, 2] *= v.metres
    names = set(las.point_format.dimension_names)
    rgb = None
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=-1)
    intensity = np.asarray(las.intensity) if "intensity" in names else None
    info.update({"format": f"LAS {header.version} point format {header.point_format.id}",
                 "scale": [float(s) for s in header.scales], "offset": [float(o) for o in header.offsets]})
    return TlsCloud(xyz, rgb, intensity, None, info)


def _first_line(exc: BaseException) -> str:
    """An exception's first line: libE57 appends an 8-line debug dump to its messages."""
    text = str(exc).strip()
    return text.splitlines()[0].strip() if text else type(exc).__name__


def _e57_metadata(root: Any) -> dict[str, Any]:
    """The E57's coordinate metadata (a CRS as text, often WKT) and identity, for the summary."""
    from pye57 import libe57

    info: dict[str, Any] = {"unit": "metre (the E57 standard)"}
    for name in ("coordinateMetadata", "guid", "creationDateTime"):
        if not root.isDefined(name):
            continue
        node = root.get(name)
        try:
            if node.type() == libe57.NodeType.E57_STRING:
                info[name] = libe57.StringNode(node).value()
            elif name == "creationDateTime":
                info[name] = libe57.FloatNode(libe57.StructureNode(node).get("dateTimeValue")).value()
        except Exception:
            continue
    if not info.get("coordinateMetadata"):
        info["coordinateMetadata"] = None  # said: the file names no coordinate system
    return info


def open_e57(path: Path) -> Any:
    """An E57 opened, with at least one scan of points (its headers only), else refused in one line."""
    try:
        import pye57
    except ImportError as exc:
        raise InputError(path, f"E57 needs the optional package 'pye57' ({TLS_EXTRA}), "
                               "or convert the cloud to PLY") from exc
    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:
        text = _first_line(exc)
        if re.search(r"BadFileLength|size in file header", text):
            why = "cut short: the file is shorter than its header says"
        elif re.search(r"Signature|Internal", text):
            why = "not an E57 file, or its writer was stopped before it finished the file"
        else:
            why = "cannot read E57"
        raise InputError(path, f"{why} ({text})") from exc
    if e57.scan_count == 0:
        raise InputError(path, "holds no scan (its writer may have stopped before writing one): no points to "
                               "mesh a reference from")
    try:
        points = sum(int(e57.get_header(i).point_count) for i in range(e57.scan_count))
    except Exception as exc:
        raise InputError(path, f"cannot read E57 ({type(exc).__name__}: {_first_line(exc)})") from exc
    if points == 0:
        raise InputError(path, f"holds no points ({e57.scan_count} empty scan(s)): nothing to mesh a "
                               "reference from")
    return e57


def read_e57(path: Path) -> TlsCloud:
    """An E57's scans in float64 (each scan's pose applied), intensity or RGB, station origins."""
    e57 = open_e57(path)
    parts, colours, intens = [], [], []
    stations: list[tuple[int, int, np.ndarray | None]] = []
    try:
        for i in range(e57.scan_count):
            header = e57.get_header(i)
            fields = set(header.point_fields)
            has_rgb = {"colorRed", "colorGreen", "colorBlue"} <= fields
            has_i = "intensity" in fields
            if header.point_count == 0:
                d: dict[str, Any] = {k: np.zeros(0) for k in ("cartesianX", "cartesianY", "cartesianZ")}
                has_rgb = has_i = False
            else:
                d = e57.read_scan(i, intensity=has_i, colors=has_rgb, ignore_missing_fields=True,
                                  transform=True)
            parts.append(np.stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]], axis=-1))
            start = sum(len(p) for p in parts[:-1])
            origin = np.asarray(header.translation, dtype=np.float64) if header.has_pose() else None
            stations.append((start, start + len(parts[-1]), origin))
            if has_rgb:
                colours.append(np.stack([d["colorRed"], d["colorGreen"], d["colorBlue"]], axis=-1))
            if has_i:
                intens.append(np.asarray(d["intensity"]))
        info = _e57_metadata(e57.root)
    except Exception as exc:
        raise InputError(path, f"cannot read E57 ({type(exc).__name__}: {_first_line(exc)})") from exc
    xyz = np.concatenate(parts).astype(np.float64)
    if len(xyz) == 0:
        raise InputError(path, f"holds no points ({e57.scan_count} empty scan(s)): nothing to mesh a "
                               "reference from")
    rgb = np.concatenate(colours) if len(colours) == len(parts) and colours else None
    intensity = np.concatenate(intens) if len(intens) == len(parts) and intens else None
    scans = None
    if all(o is not None for _, _, o in stations):  # else no station to orient towards
        scans = [(a, b, o) for a, b, o in stations if o is not None]
    info["scans"] = int(e57.scan_count)
    return TlsCloud(xyz, rgb, intensity, scans, info)
