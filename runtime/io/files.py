"""Read and write point clouds: VoD/KITTI ``.bin``, Astyx ``.txt``, ``.npy``, ``.pcd``, ``.ply``.

Reading checks sizes before allocating (a ``.bin`` must be a whole number of rows; at most
``max_points`` rows per file), drops rows with NaN/Inf and counts them in
``PointCloud.dropped_nonfinite``, and turns every kind of bad input into one
``MsdnetError(path, cause)``. Values beyond the float32 range count as non-finite (they would
become Inf). A file must hold exactly what its header states (``check_held``, the one rule of
every reader with a header, PointCloud2 messages included): a PCD whose ``POINTS`` (or
``WIDTH`` x ``HEIGHT``) differs from the rows its body holds, a PLY whose vertex count differs
from its body, an ``.npy`` whose shape differs from its bytes are refused, naming both counts;
none is silently cut. An empty
``.bin`` (what a scan with no output point writes) reads back as zero rows when its layout is
known (``columns=``, ``kind=`` or the path).

Writing is atomic (``io.atomic.atomic_output``: a temporary file in the same folder, then
``os.replace``) and keeps column names where the format can (PCD fields, PLY properties); ``.bin``
and plain ``.npy`` store bare float32 rows, read back with ``columns=``. A failed write raises
``MsdnetError`` naming the output, and says when the disk is full.

Known ``.bin`` layouts (``kind``):

- ``"vod_radar"``: float32 x7 ``x y z rcs v_r v_r_compensated time`` (VoD radar, any scan count);
- ``"lidar"``: float32 x4 ``x y z intensity`` (KITTI / VoD Velodyne).

Astyx ``.txt`` files carry a header line (radar: a blank line first, then ``X Y Z V_r Mag``;
LiDAR: ``X Y Z Reflectivity LaserID Timestamp``); names are taken from it. Values are kept as
float32, so Astyx LiDAR ``timestamp`` (~3.7e8 us) is rounded to a multiple of 32 us.

``.pcd`` and ``.ply`` need the ``formats`` extra (pypcd4, plyfile), imported when such a file is
read or written; without it, that read or write is one ``MsdnetError`` naming the extra.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import PointCloud, canonical_column
from msdnet.runtime.errors import MsdnetError, import_extra
from msdnet.runtime.io.atomic import atomic_output

MAX_POINTS = 5_000_000  # rows per file; larger files are refused before allocating
VOD_RADAR_COLUMNS = ("x", "y", "z", "rcs", "v_r", "v_r_compensated", "time")
LIDAR_COLUMNS = ("x", "y", "z", "intensity")
BIN_KINDS: dict[str, tuple[str, ...]] = {"vod_radar": VOD_RADAR_COLUMNS, "lidar": LIDAR_COLUMNS}
READ_FORMATS = (".bin", ".txt", ".npy", ".pcd", ".ply")
WRITE_FORMATS = ("bin", "npy", "pcd", "ply")
DENSE_COLUMNS = ("x", "y", "z", "confidence")  # columns of every cloud msdnet-infer writes


def read_cloud(
    path: str | Path,
    kind: str | None = None,
    columns: Sequence[str] | None = None,
    max_points: int = MAX_POINTS,
) -> PointCloud:
    """Load one point-cloud file.

    ``kind`` (``"vod_radar"`` / ``"lidar"``) fixes the layout of a ``.bin``; without it the
    layout comes from the path (a ``radar*`` folder -> radar; ``lidar``/``velodyne`` -> LiDAR),
    else from the size when only one of 28 / 16 bytes divides it. ``columns`` gives the column
    names of a headerless file (``.bin``, ``.npy``) explicitly and overrides ``kind``.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in READ_FORMATS:
        raise MsdnetError(p, f"unknown point-cloud extension {suffix!r} (read: {READ_FORMATS})")
    if kind is not None and kind not in BIN_KINDS:
        raise MsdnetError(p, f"unknown kind {kind!r} (known: {', '.join(BIN_KINDS)})")
    try:
        size = p.stat().st_size
    except OSError as err:
        raise MsdnetError(p, f"cannot read file ({err.strerror or err})") from None
    if not p.is_file():
        raise MsdnetError(p, "not a regular file")
    if size == 0 and suffix != ".bin":  # an empty .bin is a cloud of zero rows
        raise MsdnetError(p, "empty file")
    cols = None if columns is None else tuple(canonical_column(c) for c in columns)
    readers = {".bin": _read_bin, ".txt": _read_txt, ".npy": _read_npy}
    readers |= {".pcd": _read_pcd, ".ply": _read_ply}
    try:
        array, names = readers[suffix](p, size, kind, cols, max_points)
    except MsdnetError:
        raise
    except Exception as err:  # third-party parsers raise many types on broken content
        cause = " ".join(str(err).split())[:200] or type(err).__name__
        raise MsdnetError(p, f"unreadable {suffix} content: {cause}") from None
    return cloud_from_array(p, array, names)


def cloud_from_array(path: str | Path, array: np.ndarray, names: tuple[str, ...]) -> PointCloud:
    """(N, C) array [``names``] read from ``path`` -> float32 PointCloud with non-finite rows (and
    values beyond float32) dropped and counted in ``dropped_nonfinite``."""
    if array.ndim != 2 or array.shape[1] != len(names):
        raise MsdnetError(path, f"got {array.shape} values for columns {' '.join(names)}")
    if len(set(names)) != len(names):
        raise MsdnetError(path, f"duplicate column names: {' '.join(names)}")
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32 -> Inf, dropped below
        pts = np.ascontiguousarray(array, dtype=np.float32)
    finite = np.isfinite(pts).all(axis=1)
    dropped = int(pts.shape[0] - finite.sum())
    if dropped:
        pts = pts[finite]
    return PointCloud(pts, names, dropped_nonfinite=dropped, source=str(path))


def check_held(path: str | Path | None, unit: str, stated: int, held: int, row_bytes: int = 0) -> None:
    """The one rule of every reader with a header: the body holds exactly what the header states.

    ``held``: the rows the body holds, or with ``row_bytes`` the body's size in bytes (rows of
    ``row_bytes`` each, a partial row counted apart). MsdnetError naming both counts otherwise:
    a header that understates its body would cut rows silently, one that overstates it would
    read past the end."""
    rest = 0
    if row_bytes:
        held, rest = divmod(held, row_bytes)
    if held != stated or rest:
        tail = f" and {rest} more bytes" if rest else ""
        raise MsdnetError(path, f"header states {stated} {unit}, the data holds {held}{tail}")


def _too_many(path: Path, n: int, max_points: int) -> None:
    if n > max_points:
        raise MsdnetError(path, f"{n} points exceeds the cap of {max_points} per file")


def _bin_kind_from_path(path: Path) -> str | None:
    parents = [part.lower() for part in path.parent.parts[-4:]]
    if any(part.startswith("radar") for part in parents):
        return "vod_radar"
    if any(part in ("lidar", "velodyne") or part.startswith("lidar") for part in parents):
        return "lidar"
    return None


def _read_bin(path: Path, size: int, kind: str | None, cols, max_points: int):
    if cols is None:
        kind = kind or _bin_kind_from_path(path)
        if kind is None:
            if size == 0:
                raise MsdnetError(path, "empty .bin (no rows) of unknown layout; pass columns= or kind=")
            fits = [k for k, c in BIN_KINDS.items() if size % (4 * len(c)) == 0]
            if len(fits) != 1:
                raise MsdnetError(
                    path,
                    f"cannot tell VoD radar (7 float32) from LiDAR (4 float32) by path or size "
                    f"({size} bytes); pass kind='vod_radar' or kind='lidar'",
                )
            kind = fits[0]
        cols = BIN_KINDS[kind]
    row_bytes = 4 * len(cols)
    if size % row_bytes:
        raise MsdnetError(
            path,
            f"size {size} bytes is not a whole number of {len(cols)}-column float32 rows "
            f"({row_bytes} bytes each)",
        )
    n = size // row_bytes
    _too_many(path, n, max_points)
    return np.fromfile(path, dtype="<f4").reshape(n, len(cols)), cols  # (N, C)


def _read_txt(path: Path, size: int, kind: str | None, cols, max_points: int):
    header_idx, header = -1, None
    lines = 0
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            lines += chunk.count(b"\n")
        f.seek(0)
        for i, raw in enumerate(f):
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise MsdnetError(path, "not a text point file (non-ASCII bytes)") from None
            if line:
                header_idx, header = i, line.split()
                break
    if header is None:
        raise MsdnetError(path, "no rows (blank file)")
    _too_many(path, lines - header_idx, max_points)
    has_header = not all(_is_number(tok) for tok in header)
    skip = header_idx + 1 if has_header else header_idx
    if has_header:
        names = tuple(canonical_column(tok) for tok in header)
    else:
        names = cols or _default_columns(len(header), kind)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            data = np.loadtxt(path, dtype=np.float64, skiprows=skip, ndmin=2, encoding="ascii")
    except ValueError as err:
        cause = " ".join(str(err).split())[:160]
        raise MsdnetError(path, f"unreadable rows: {cause}") from None
    if data.shape[0] == 0:
        data = np.zeros((0, len(names)), dtype=np.float64)
    if data.shape[1] != len(names):
        raise MsdnetError(path, f"rows have {data.shape[1]} values, header names {len(names)}")
    return data, names


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _default_columns(width: int, kind: str | None) -> tuple[str, ...]:
    """Names for headerless data: a known layout of that width, else ``x y z f3 f4 ...``."""
    if kind is not None and len(BIN_KINDS[kind]) == width:
        return BIN_KINDS[kind]
    for known in BIN_KINDS.values():
        if len(known) == width:
            return known
    return ("x", "y", "z", *(f"f{i}" for i in range(3, width)))


def _read_npy(path: Path, size: int, kind: str | None, cols, max_points: int):
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        body = size - f.tell()
    if len(shape) >= 1 and not dtype.hasobject and dtype.itemsize:
        rows = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
        if rows:
            check_held(path, "rows", int(shape[0]), body, rows)
    if dtype.names is not None:  # structured array: one named field per column
        if len(shape) != 1:
            raise MsdnetError(path, f"structured array must be 1-D, got shape {shape}")
        _too_many(path, shape[0], max_points)
        arr = np.load(path, allow_pickle=False)
        names = tuple(canonical_column(n) for n in dtype.names)
        fields = [np.asarray(arr[n], dtype=np.float64) for n in dtype.names]
        return np.stack(fields, axis=1).reshape(shape[0], len(names)), names
    if len(shape) != 2 or shape[1] < 3:
        raise MsdnetError(path, f"array must be (N, >=3), got shape {shape}")
    if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)):
        raise MsdnetError(path, f"array dtype {dtype} is not a real number type")
    _too_many(path, shape[0], max_points)
    names = cols or _default_columns(shape[1], kind)
    return np.load(path, allow_pickle=False), names


def _pcd() -> Any:
    return import_extra("pypcd4", ".pcd files")


def _ply() -> Any:
    return import_extra("plyfile", ".ply files")


def _read_pcd(path: Path, size: int, kind: str | None, cols, max_points: int):
    pypcd4 = _pcd()
    with open(path, "rb") as f:
        lines: list[str] = []
        for raw in f:  # the header, as pypcd4 reads it, to check the count before the data
            line = raw.decode("utf-8", errors="replace").strip()
            if not line or line.startswith("#"):
                continue
            lines.append(line)
            if line.startswith("DATA") or len(lines) >= 10:
                break
        if not lines or not lines[-1].startswith("DATA"):
            raise MsdnetError(path, "no PCD header (VERSION ... DATA lines)")
        body_start = f.tell()
        meta = pypcd4.MetaData.parse_header(lines)
        _too_many(path, meta.points, max_points)
        if any(c != 1 for c in meta.count):
            raise MsdnetError(path, "PCD fields with COUNT > 1 are not supported")
        if meta.width * meta.height != meta.points:
            raise MsdnetError(
                path,
                f"header states WIDTH {meta.width} x HEIGHT {meta.height} points but POINTS {meta.points}",
            )
        if meta.data == "binary":
            check_held(path, "points", meta.points, size - body_start, sum(meta.size))
        elif meta.data == "ascii":
            f.seek(body_start)
            check_held(path, "points", meta.points, sum(1 for line in f if line.strip()))
        f.seek(0)
        pc = pypcd4.PointCloud.from_fileobj(f)
    names = tuple(canonical_column(n) for n in pc.fields)
    data = pc.numpy().astype(np.float64).reshape(-1, len(names))  # (N, C)
    check_held(path, "points", meta.points, data.shape[0])
    return data, names


def _read_ply(path: Path, size: int, kind: str | None, cols, max_points: int):
    plyfile = _ply()
    with open(path, "rb") as f:
        header = plyfile.PlyData._parse_header(f)  # header only: element counts
        body_start = f.tell()
    if "vertex" not in header:
        raise MsdnetError(path, "PLY file has no 'vertex' element")
    _too_many(path, header["vertex"].count, max_points)
    _ply_holds_no_more(path, size, header, body_start)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    props = [pr.name for pr in vertex.properties if not isinstance(pr, plyfile.PlyListProperty)]
    data = vertex.data
    fields = [np.asarray(data[n], dtype=np.float64) for n in props]
    names = tuple(canonical_column(n) for n in props)
    return np.stack(fields, axis=1).reshape(len(data), len(names)), names  # (N, C)


def _ply_holds_no_more(path: Path, size: int, header: Any, body_start: int) -> None:
    """Refuse a PLY whose body holds more or fewer vertices than its header states (plyfile
    reads the stated count and ignores the rest): text, by non-blank lines; binary, by bytes
    (fixed-size properties only)."""
    plyfile = _ply()
    elements, count = header.elements, header["vertex"].count
    others = [e for e in elements if e.name != "vertex"]
    if header.text:
        with open(path, "rb") as f:
            f.seek(body_start)
            lines = sum(1 for line in f if line.strip())
        check_held(path, "vertices", count, lines - sum(e.count for e in others))
        return
    if any(isinstance(pr, plyfile.PlyListProperty) for e in elements for pr in e.properties):
        return
    row = {e.name: sum(np.dtype(pr.val_dtype).itemsize for pr in e.properties) for e in elements}
    if row["vertex"]:
        body = size - body_start - sum(e.count * row[e.name] for e in others)
        check_held(path, "vertices", count, body, row["vertex"])


def write_cloud(path: str | Path, cloud: PointCloud, fmt: str | None = None) -> Path:
    """Write ``cloud`` atomically as ``.bin`` / ``.npy`` / ``.pcd`` / ``.ply``; returns the path.

    ``.bin``: float32 rows as is (read back with ``columns=cloud.columns`` unless the layout is
    a known one); ``.npy``: (N, C) float32; ``.pcd`` / ``.ply``: float32 fields named by column.
    """
    target = Path(path)
    kind = (fmt or target.suffix.lstrip(".")).lower()
    if kind not in WRITE_FORMATS:
        raise MsdnetError(target, f"cannot write format {kind!r} (write: {WRITE_FORMATS})")
    pts = np.ascontiguousarray(cloud.points, dtype="<f4")  # (N, C)
    lib = {"pcd": _pcd, "ply": _ply}.get(kind, lambda: None)()  # before the temporary file
    with atomic_output(target) as tmp, open(tmp, "wb") as f:
        if kind == "bin":
            pts.tofile(f)
        elif kind == "npy":
            np.save(f, pts, allow_pickle=False)
        elif kind == "pcd":
            pc = lib.PointCloud.from_points(pts, cloud.columns, [np.float32] * len(cloud.columns))
            pc.save(f)
        else:
            rows = np.empty(len(pts), dtype=[(c, "<f4") for c in cloud.columns])
            for i, c in enumerate(cloud.columns):
                rows[c] = pts[:, i]
            lib.PlyData([lib.PlyElement.describe(rows, "vertex")], text=False).write(f)
    return target


def write_dense(path: str | Path, points: np.ndarray, confidence: np.ndarray, fmt: str | None = None) -> Path:
    """Write a dense output atomically: points (M, 3) float32 [x, y, z] and confidence (M,) as
    columns ``DENSE_COLUMNS``; returns the path."""
    dense = np.concatenate([points, confidence[:, None]], axis=1)  # (M, 4)
    return write_cloud(path, PointCloud(dense, DENSE_COLUMNS, source=str(path)), fmt)
