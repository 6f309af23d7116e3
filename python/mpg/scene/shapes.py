"""Triangle meshes: file readers (OBJ, PLY, Mitsuba serialized), tessellation
of Mitsuba's parametric shapes, transforms and vertex normals.

All readers return a `Mesh` in the file's own space with float64 positions and
int64 indices; the loader transforms, validates and converts it. Problems in a
mesh file raise SceneError naming the mesh file (and its line for OBJ / ASCII
PLY where it is known).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from itertools import chain

import numpy as np

from mpg.errors import SceneError


@dataclass
class Mesh:
    positions: np.ndarray                  # (N, 3) float64
    indices: np.ndarray                    # (M, 3) int64
    normals: np.ndarray | None = None   # (N, 3) float64
    uvs: np.ndarray | None = None       # (N, 2) float64
    normals_partial: bool = False          # some OBJ corners had no normal


# ---------------------------------------------------------------------------
# Generic helpers

def _parse_floats(text: str, fname: str, what: str) -> np.ndarray:
    try:
        return np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise SceneError(f"could not parse the {what} as numbers", fname) from None


def vertex_normals(positions: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Angle-weighted vertex normals (the weighting Mitsuba uses); vertices of
    degenerate faces only get zero vectors."""
    p = positions[indices]                           # (M, 3, 3)
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = np.linalg.norm(fn, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        fn = np.where(ln > 0, fn / ln, 0.0)
    n = np.zeros_like(positions)
    for k in range(3):
        e1 = p[:, (k + 1) % 3] - p[:, k]
        e2 = p[:, (k + 2) % 3] - p[:, k]
        l1 = np.linalg.norm(e1, axis=1)
        l2 = np.linalg.norm(e2, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.einsum("ij,ij->i", e1, e2) / (l1 * l2)
        ang = np.arccos(np.clip(np.nan_to_num(c, nan=1.0), -1.0, 1.0))
        w = fn * ang[:, None]
        for d in range(3):
            n[:, d] += np.bincount(indices[:, k], weights=w[:, d], minlength=len(positions))
    return n


def normalize_rows(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit rows and a mask of rows whose length was (near) zero."""
    ln = np.linalg.norm(v, axis=1)
    bad = ~(ln > 1e-20)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = v / np.where(bad, 1.0, ln)[:, None]
    return out, bad


def transform_mesh(mesh: Mesh, m: np.ndarray) -> Mesh:
    """Apply a 4x4 affine transform; normals by the inverse transpose."""
    a = m[:3, :3]
    pos = mesh.positions @ a.T + m[:3, 3]
    normals = None
    if mesh.normals is not None:
        try:
            nm = np.linalg.inv(a).T
        except np.linalg.LinAlgError:
            nm = None
        if nm is not None:
            normals = mesh.normals @ nm.T
    return Mesh(pos, mesh.indices, normals, mesh.uvs, mesh.normals_partial)


# ---------------------------------------------------------------------------
# Wavefront OBJ

def read_obj(path: str, flip_tex_coords: bool = True) -> Mesh:
    """Read an OBJ file: v/vt/vn/f, polygons fan-triangulated, negative indices,
    all objects and groups merged. Corners are deduplicated by their
    (v, vt, vn) triple as Mitsuba does, so a file without vt/vn gives a shared-
    vertex mesh. Texture v is flipped (1 - v) when flip_tex_coords is set,
    Mitsuba's default."""
    with open(path, "rb") as f:
        data = f.read()
    text = data.decode("utf-8", errors="replace").replace("\t", " ")
    lines = text.splitlines()
    V: list[str] = []
    VT: list[str] = []
    VN: list[str] = []
    F: list[str] = []
    f_line: list[int] = []
    f_counts: list[tuple[int, int, int]] = []
    for ln, raw in enumerate(lines, 1):
        s = raw.lstrip()
        c = s[:2]
        if c == "v ":
            V.append(s[2:])
        elif c == "vt" and s[2:3] == " ":
            VT.append(s[3:])
        elif c == "vn" and s[2:3] == " ":
            VN.append(s[3:])
        elif c == "f ":
            F.append(s[2:])
            f_line.append(ln)
            f_counts.append((len(V), len(VT), len(VN)))

    def table(rows: list[str], k: int, what: str, pad: float | None = None) -> np.ndarray:
        if not rows:
            return np.zeros((0, k))
        arr = _parse_floats(" ".join(rows), path, what)
        if arr.size == k * len(rows):
            return arr.reshape(-1, k)
        out = np.zeros((len(rows), k))
        for i, r in enumerate(rows):
            vals = r.split()
            if len(vals) < k and pad is None:
                raise SceneError(f"{what}: a line has {len(vals)} values, expected {k}", path)
            vals = (vals + [str(pad)] * k)[:k]
            try:
                out[i] = [float(x) for x in vals]
            except ValueError:
                raise SceneError(f"could not parse the {what} as numbers", path) from None
        return out

    pos = table(V, 3, "vertex positions ('v')")
    tex = table(VT, 2, "texture coordinates ('vt')", pad=0.0)
    nrm = table(VN, 3, "vertex normals ('vn')")
    if not F:
        raise SceneError("mesh has no faces ('f' lines)", path)

    corners = [r.split() for r in F]
    counts = np.fromiter((len(c) for c in corners), dtype=np.int64, count=len(corners))
    small = np.nonzero(counts < 3)[0]
    if small.size:
        raise SceneError("face with fewer than 3 vertices", path, f_line[int(small[0])])
    flat = list(chain.from_iterable(corners))
    nslash = flat[0].count("/")
    fast = nslash <= 2 and all(c.count("/") == nslash for c in flat)
    if fast:
        joined = " ".join(flat)
        if "//" in joined:
            joined = joined.replace("//", "/0/")
        k = nslash + 1
        try:
            ids = np.array(joined.replace("/", " ").split(), dtype=np.int64)
        except (ValueError, OverflowError):
            ids = None
        if ids is not None and ids.size == len(flat) * k:
            ids = ids.reshape(-1, k)
            if k < 3:
                ids = np.concatenate([ids, np.zeros((len(ids), 3 - k), np.int64)], axis=1)
        else:
            fast = False
    if not fast:
        ids = np.zeros((len(flat), 3), np.int64)
        fi = np.repeat(np.arange(len(F)), counts)
        for i, c in enumerate(flat):
            parts = c.split("/")
            if len(parts) > 3:
                raise SceneError(f"bad face vertex '{c}'", path, f_line[int(fi[i])])
            for j, p in enumerate(parts):
                if p == "":
                    continue
                try:
                    ids[i, j] = int(p)
                except ValueError:
                    raise SceneError(f"bad face vertex '{c}'", path, f_line[int(fi[i])]) from None

    face_of_corner = np.repeat(np.arange(len(F)), counts)
    prior = np.asarray(f_counts, dtype=np.int64)[face_of_corner]       # (C, 3)
    totals = (len(pos), len(tex), len(nrm))
    names = ("vertex", "texture coordinate", "normal")
    resolved = np.empty_like(ids)
    for j in range(3):
        col = ids[:, j]
        r = np.where(col > 0, col - 1, prior[:, j] + col)
        r = np.where(col == 0, -1, r)
        if j == 0:
            bad = (col == 0) | (r < 0) | (r >= totals[0])
        else:
            bad = (col != 0) & ((r < 0) | (r >= totals[j]))
        if bad.any():
            i = int(np.argmax(bad))
            raise SceneError(f"face refers to {names[j]} {int(col[i])}, but the file has "
                             f"{totals[j]} of them", path, f_line[int(face_of_corner[i])])
        resolved[:, j] = r

    has_vt = resolved[:, 1] >= 0
    has_vn = resolved[:, 2] >= 0
    nt, nn = totals[1] + 1, totals[2] + 1
    if totals[0] * nt * nn < 2 ** 62:
        key = resolved[:, 0] * (nt * nn) + (resolved[:, 1] + 1) * nn + (resolved[:, 2] + 1)
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(resolved, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    rep = resolved[first]
    positions = pos[rep[:, 0]]
    uvs = None
    if has_vt.any():
        uvs = np.where((rep[:, 1] >= 0)[:, None], tex[np.maximum(rep[:, 1], 0)], 0.0)
        if flip_tex_coords:
            uvs[:, 1] = 1.0 - uvs[:, 1]
    normals = None
    partial = False
    if has_vn.all():
        normals = nrm[rep[:, 2]]
    elif has_vn.any():
        partial = True

    # fan triangulation
    start = np.cumsum(counts) - counts
    ntri = counts - 2
    T = int(ntri.sum())
    face = np.repeat(np.arange(len(F)), ntri)
    within = np.arange(T) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    s = start[face]
    tri = np.stack([s, s + 1 + within, s + 2 + within], axis=1)
    indices = inverse[tri]
    return Mesh(positions, indices.astype(np.int64), normals, uvs, partial)


# ---------------------------------------------------------------------------
# Stanford PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply(path: str) -> Mesh:
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith(b"ply"):
        raise SceneError("not a PLY file (missing 'ply' magic)", path, 1)
    end = data.find(b"end_header")
    if end < 0:
        raise SceneError("PLY header has no 'end_header'", path)
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for ln, line in enumerate(header, 1):
        t = line.split()
        if not t or t[0] in ("ply", "comment", "obj_info"):
            continue
        try:
            if t[0] == "format":
                fmt = t[1]
            elif t[0] == "element":
                elements.append((t[1], int(t[2]), []))
            elif t[0] == "property":
                if not elements:
                    raise SceneError("PLY property before any element", path, ln)
                if t[1] == "list":
                    elements[-1][2].append((t[4], "list", _PLY_TYPES[t[2]], _PLY_TYPES[t[3]]))
                else:
                    elements[-1][2].append((t[2], "scalar", _PLY_TYPES[t[1]], None))
            else:
                raise SceneError(f"unknown PLY header line '{line.strip()}'", path, ln)
        except (IndexError, KeyError, ValueError):
            raise SceneError(f"bad PLY header line '{line.strip()}'", path, ln) from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneError(f"unsupported PLY format '{fmt}'", path)
    if any(cnt < 0 for _, cnt, _ in elements):
        raise SceneError("negative PLY element count", path)
    body = data[body_start:]
    values: dict[str, dict[str, object]] = {}
    if fmt == "ascii":
        try:
            tokens = np.array(body.split(), dtype=np.float64)
        except ValueError:
            raise SceneError("PLY body contains non-numeric data", path) from None
        pos = 0
        for name, cnt, props in elements:
            values[name], pos = _ply_ascii_element(tokens, pos, cnt, props, path)
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        pos = 0
        for name, cnt, props in elements:
            values[name], pos = _ply_binary_element(body, pos, cnt, props, bo, path)
    return _ply_mesh(values, path)


def _ply_ascii_element(tokens, pos, cnt, props, path):
    out: dict[str, object] = {}
    if cnt == 0:
        return {p[0]: np.zeros(0) for p in props}, pos
    if all(p[1] == "scalar" for p in props):
        n = len(props) * cnt
        if pos + n > tokens.size:
            raise SceneError("PLY file is truncated", path)
        block = tokens[pos:pos + n].reshape(cnt, len(props))
        return {p[0]: block[:, i] for i, p in enumerate(props)}, pos + n
    if len(props) == 1:  # a single list property: try constant length
        c = int(tokens[pos]) if pos < tokens.size else -1
        n = (c + 1) * cnt
        if c >= 0 and pos + n <= tokens.size:
            block = tokens[pos:pos + n].reshape(cnt, c + 1)
            if np.all(block[:, 0] == c):
                out[props[0][0]] = block[:, 1:]
                return out, pos + n
    rows: dict[str, list] = {p[0]: [] for p in props}
    for _ in range(cnt):
        for p in props:
            if pos >= tokens.size:
                raise SceneError("PLY file is truncated", path)
            if p[1] == "scalar":
                rows[p[0]].append(tokens[pos])
                pos += 1
            else:
                c = int(tokens[pos])
                if c < 0 or pos + 1 + c > tokens.size:
                    raise SceneError("PLY file is truncated or has a bad list length", path)
                rows[p[0]].append(tokens[pos + 1:pos + 1 + c])
                pos += 1 + c
    for p in props:
        out[p[0]] = np.array(rows[p[0]]) if p[1] == "scalar" else rows[p[0]]
    return out, pos


def _ply_binary_element(body, pos, cnt, props, bo, path):
    if all(p[1] == "scalar" for p in props):
        dt = np.dtype([(f"p{i}", bo + p[2]) for i, p in enumerate(props)])
        n = dt.itemsize * cnt
        if pos + n > len(body):
            raise SceneError("PLY file is truncated", path)
        arr = np.frombuffer(body, dtype=dt, count=cnt, offset=pos)
        return {p[0]: arr[f"p{i}"].astype(np.float64) for i, p in enumerate(props)}, pos + n
    if cnt == 0:
        return {p[0]: [] for p in props}, pos
    # fast path: every list has the length of the first one
    fields = []
    off = pos
    lens = []
    for i, p in enumerate(props):
        if p[1] == "scalar":
            fields.append((f"p{i}", bo + p[2]))
            off += np.dtype(p[2]).itemsize
        else:
            ct = np.dtype(bo + p[2])
            if off + ct.itemsize > len(body):
                raise SceneError("PLY file is truncated", path)
            c = int(np.frombuffer(body, dtype=ct, count=1, offset=off)[0])
            lens.append(c)
            fields.append((f"c{i}", bo + p[2]))
            fields.append((f"p{i}", bo + p[3], (c,)) if c > 0 else (f"p{i}", bo + p[3], (0,)))
            off += ct.itemsize + c * np.dtype(p[3]).itemsize
    dt = np.dtype(fields)
    n = dt.itemsize * cnt
    if pos + n <= len(body):
        arr = np.frombuffer(body, dtype=dt, count=cnt, offset=pos)
        ok = all(np.all(arr[f"c{i}"] == lens[j]) for j, i in
                 enumerate(i for i, p in enumerate(props) if p[1] == "list"))
        if ok:
            return {p[0]: arr[f"p{i}"].astype(np.float64) if p[1] == "scalar" else arr[f"p{i}"]
                    for i, p in enumerate(props)}, pos + n
    rows: dict[str, list] = {p[0]: [] for p in props}
    for _ in range(cnt):
        for p in props:
            if p[1] == "scalar":
                t = np.dtype(bo + p[2])
                if pos + t.itemsize > len(body):
                    raise SceneError("PLY file is truncated", path)
                rows[p[0]].append(float(np.frombuffer(body, t, 1, pos)[0]))
                pos += t.itemsize
            else:
                ct, it = np.dtype(bo + p[2]), np.dtype(bo + p[3])
                if pos + ct.itemsize > len(body):
                    raise SceneError("PLY file is truncated", path)
                c = int(np.frombuffer(body, ct, 1, pos)[0])
                pos += ct.itemsize
                if c < 0 or pos + c * it.itemsize > len(body):
                    raise SceneError("PLY file is truncated or has a bad list length", path)
                rows[p[0]].append(np.frombuffer(body, it, c, pos))
                pos += c * it.itemsize
    return {p[0]: (np.array(rows[p[0]]) if p[1] == "scalar" else rows[p[0]]) for p in props}, pos


def _ply_mesh(values, path) -> Mesh:
    v = values.get("vertex")
    f = values.get("face")
    if v is None or f is None:
        raise SceneError("PLY file needs 'vertex' and 'face' elements", path)
    try:
        positions = np.stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"], axis=1)
    except KeyError:
        raise SceneError("PLY vertices need x, y, z properties", path) from None
    normals = None
    if all(c in v for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(v[c], dtype=np.float64) for c in ("nx", "ny", "nz")], axis=1)
    uvs = None
    for a, b in (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t")):
        if a in v and b in v:
            uvs = np.stack([np.asarray(v[a], dtype=np.float64), np.asarray(v[b], dtype=np.float64)],
                           axis=1)
            break
    lst = f.get("vertex_indices", f.get("vertex_index"))
    if lst is None:
        raise SceneError("PLY faces need a 'vertex_indices' list", path)
    if isinstance(lst, np.ndarray) and lst.ndim == 2:
        polys = lst.astype(np.int64)
        if polys.shape[1] < 3:
            raise SceneError("PLY face with fewer than 3 vertices", path)
        k = polys.shape[1]
        tris = np.concatenate([np.stack([polys[:, 0], polys[:, i], polys[:, i + 1]], axis=1)
                               for i in range(1, k - 1)], axis=0) if len(polys) else \
            np.zeros((0, 3), np.int64)
    else:
        out = []
        for poly in lst:
            poly = np.asarray(poly, dtype=np.int64)
            if len(poly) < 3:
                raise SceneError("PLY face with fewer than 3 vertices", path)
            for i in range(1, len(poly) - 1):
                out.append((poly[0], poly[i], poly[i + 1]))
        tris = np.array(out, dtype=np.int64).reshape(-1, 3)
    return Mesh(positions, tris, normals, uvs)


# ---------------------------------------------------------------------------
# Mitsuba serialized

def read_serialized(path: str, shape_index: int = 0, flip_tex_coords: bool = True) -> Mesh:
    """Mitsuba's .serialized format (version 3 and 4): a table of zlib-compressed
    shapes; `shape_index` picks one."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 8 or struct.unpack("<H", data[:2])[0] != 0x041C:
        raise SceneError("not a Mitsuba serialized file (bad magic)", path)
    version = struct.unpack("<H", data[2:4])[0]
    if version not in (3, 4):
        raise SceneError(f"unsupported serialized version {version}", path)
    count = struct.unpack("<I", data[-4:])[0]
    if shape_index < 0 or shape_index >= count:
        raise SceneError(f"shape_index {shape_index} out of range (file has {count} shapes)", path)
    osz = 8 if version == 4 else 4
    table_start = len(data) - 4 - osz * count
    if table_start < 4:
        raise SceneError("serialized file is truncated", path)
    offset = struct.unpack("<Q" if osz == 8 else "<I",
                           data[table_start + osz * shape_index: table_start + osz * (shape_index + 1)])[0]
    try:
        raw = zlib.decompressobj().decompress(data[offset + 4:])
    except zlib.error as e:
        raise SceneError(f"corrupt serialized data: {e}", path) from None
    try:
        p = 0
        flags = struct.unpack_from("<I", raw, p)[0]
        p += 4
        if version == 4:
            z = raw.index(b"\0", p)
            p = z + 1
        nv, nt = struct.unpack_from("<QQ", raw, p)
        p += 16
        ft = "<f8" if flags & 0x2000 else "<f4"
        fs = 8 if flags & 0x2000 else 4

        def take(n, dt, sz):
            nonlocal p
            if p + n * sz > len(raw):
                raise SceneError("serialized file is truncated", path)
            a = np.frombuffer(raw, dtype=dt, count=n, offset=p).astype(np.float64 if "f" in dt else np.int64)
            p += n * sz
            return a
        positions = take(nv * 3, ft, fs).reshape(-1, 3)
        normals = take(nv * 3, ft, fs).reshape(-1, 3) if flags & 0x0001 else None
        uvs = take(nv * 2, ft, fs).reshape(-1, 2) if flags & 0x0002 else None
        if flags & 0x0008:
            take(nv * 3, ft, fs)
        it, isz = ("<u8", 8) if nv > 0xFFFFFFFF else ("<u4", 4)
        indices = take(nt * 3, it, isz).reshape(-1, 3)
    except (struct.error, ValueError):
        raise SceneError("serialized file is truncated", path) from None
    if uvs is not None and flip_tex_coords:
        uvs = uvs.copy()
        uvs[:, 1] = 1.0 - uvs[:, 1]
    if flags & 0x0010:
        normals = None
    return Mesh(positions, indices, normals, uvs)


# ---------------------------------------------------------------------------
# Parametric shapes, in Mitsuba's local frames

def rectangle() -> Mesh:
    """[-1,1]^2 in the z=0 plane, normal +z, uv = ((x+1)/2, (y+1)/2)."""
    p = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    n = np.tile([0.0, 0.0, 1.0], (4, 1))
    return Mesh(p, np.array([[0, 1, 2], [2, 3, 0]], dtype=np.int64), n, uv)


def disk(segments: int = 256) -> Mesh:
    """Unit disk in z=0, normal +z, uv = (r, phi / 2pi). Rim vertices lie on the
    circle; the seam and the centre are duplicated so uvs stay continuous."""
    N = segments
    phi = 2 * np.pi * np.arange(N + 1) / N
    rim = np.stack([np.cos(phi), np.sin(phi), np.zeros(N + 1)], axis=1)
    rim[-1] = rim[0]
    centers = np.zeros((N, 3))
    p = np.concatenate([centers, rim])
    uv = np.concatenate([np.stack([np.zeros(N), (np.arange(N) + 0.5) / N], axis=1),
                         np.stack([np.ones(N + 1), np.arange(N + 1) / N], axis=1)])
    i = np.arange(N)
    idx = np.stack([i, N + i, N + i + 1], axis=1)
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    return Mesh(p, idx.astype(np.int64), n, uv)


def cube() -> Mesh:
    """[-1,1]^3, 24 vertices with face normals, each face mapped to [0,1]^2."""
    P, N, UV, I = [], [], [], []
    for a in range(3):
        for s in (1.0, -1.0):
            n = np.zeros(3)
            n[a] = s
            t = np.zeros(3)
            t[(a + 1) % 3] = 1.0
            b = np.zeros(3)
            b[(a + 2) % 3] = 1.0
            if s < 0:
                t, b = b, t
            base = len(P)
            for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
                P.append(n + (2 * u - 1) * t + (2 * v - 1) * b)
                N.append(n)
                UV.append((u, v))
            I += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return Mesh(np.array(P), np.array(I, dtype=np.int64), np.array(N), np.array(UV, dtype=np.float64))


def cylinder(segments: int = 128) -> Mesh:
    """Open cylinder of radius 1 around +z, z in [0, 1], outward normals exact at
    the vertices, uv = (phi / 2pi, z)."""
    N = segments
    phi = 2 * np.pi * np.arange(N + 1) / N
    c, s = np.cos(phi), np.sin(phi)
    c[-1], s[-1] = 1.0, 0.0
    bottom = np.stack([c, s, np.zeros(N + 1)], axis=1)
    top = np.stack([c, s, np.ones(N + 1)], axis=1)
    p = np.concatenate([bottom, top])
    n = np.concatenate([bottom * [1, 1, 0], bottom * [1, 1, 0]])
    u = np.arange(N + 1) / N
    uv = np.concatenate([np.stack([u, np.zeros(N + 1)], axis=1), np.stack([u, np.ones(N + 1)], axis=1)])
    i = np.arange(N)
    b0, b1, t0, t1 = i, i + 1, N + 1 + i, N + 2 + i
    idx = np.concatenate([np.stack([b0, b1, t1], axis=1), np.stack([b0, t1, t0], axis=1)])
    return Mesh(p, idx.astype(np.int64), n, uv)


def stand_in(size: float = 0.01) -> Mesh:
    """A small flat square used in place of a missing mesh file."""
    m = rectangle()
    m.positions = m.positions * size
    return m


def mesh_area(positions: np.ndarray, indices: np.ndarray) -> float:
    p = positions[indices].astype(np.float64)
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())
