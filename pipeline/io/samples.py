"""samples.npz: irregular light-field samples on the known geometry (written by stages/samples/).

Layout
------
An *uncompressed* NumPy ``.npz`` (a ZIP archive of ``.npy`` members, all ``ZIP_STORED``), one member
per field, each a C-ordered array whose first axis is the sample index (N samples, M images):

=============  ==========  =======  ===========================================================
field          shape       dtype    meaning
=============  ==========  =======  ===========================================================
point          (N, 3)      float32  surface point, world (= object) frame, metres
normal         (N, 3)      float32  unit normal: vertex normals interpolated with ``bary``
view_dir       (N, 3)      float32  unit vector FROM the surface point TO the camera centre
radiance       (N, 3)      float32  linear RGB radiance of the pixel (one scale per capture)
image_id       (N,)        int32    index into ``image_keys``
pixel          (N, 2)      int32    (row, col) of the pixel, 0-based, row 0 at the top
face           (N,)        int32    index of the hit triangle in the mesh as trimesh loads it
bary           (N, 3)      float32  barycentric coordinates of ``point`` in ``face``
weight         (N,)        float32  >= 0, multiplies the squared residual in the fit
                                    (1 for a fully valid pixel; a fractional linear mask lowers it)
visibility     (N,)        float32  cosine-weighted fraction of the hemisphere around the normal
                                    that the mesh does NOT block, in [0, 1] (1 = unshadowed;
                                    (1/pi) * integral of V(w) (n.w) dw, see docs/samples.md).
                                    Stored for every sample; the fit filters (e.g. >= 0.9).
image_keys     (M,)        str      image keys (file names relative to images/), as poses.json
meta           ()          str      JSON: schema, counts, drops per reason, coverage, settings
=============  ==========  =======  ===========================================================

Why this layout: ``np.load`` reads an npz member lazily (only the fields asked for), and because the
members are stored uncompressed, :func:`iter_sample_chunks` memory-maps each member inside the ZIP
and yields row chunks, so a fit can stream 10^7 samples with memory O(chunk). :class:`SamplesWriter`
streams the other way: rows are appended chunk by chunk (spooled to temporary files beside the
output) and the archive is assembled at the end and renamed into place atomically.

Any npz with these members can be read (e.g. one written by ``np.savez``); a compressed member is
simply loaded whole instead of memory-mapped.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import tempfile
import zipfile
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from pipeline.errors import UserError
from pipeline.io.values import json_ready
from pipeline.workdir import SPOOL_MARK, atomic_path

SCHEMA = "sigrend.samples/1"

# field -> (dtype, trailing shape).  Every field has N rows.
SAMPLE_FIELDS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "point": (np.dtype(np.float32), (3,)),
    "normal": (np.dtype(np.float32), (3,)),
    "view_dir": (np.dtype(np.float32), (3,)),
    "radiance": (np.dtype(np.float32), (3,)),
    "image_id": (np.dtype(np.int32), ()),
    "pixel": (np.dtype(np.int32), (2,)),
    "face": (np.dtype(np.int32), ()),
    "bary": (np.dtype(np.float32), (3,)),
    "weight": (np.dtype(np.float32), ()),
    "visibility": (np.dtype(np.float32), ()),
}

_COPY_BLOCK = 1 << 24  # bytes copied at a time when assembling the archive


def _check_chunk(arrays: dict[str, Any], name: str) -> dict[str, np.ndarray]:
    """Cast a dict of per-field arrays to the schema's dtypes and check shapes (all N rows)."""
    missing = [f for f in SAMPLE_FIELDS if f not in arrays]
    if missing:
        raise ValueError(f"{name}: missing sample field(s) {', '.join(missing)}")
    out: dict[str, np.ndarray] = {}
    n = None
    for field, (dtype, tail) in SAMPLE_FIELDS.items():
        arr = np.ascontiguousarray(arrays[field], dtype=dtype)
        if arr.shape[1:] != tail or arr.ndim != 1 + len(tail):
            raise ValueError(f"{name}: field {field!r} has shape {arr.shape}, expected (N, {tail})")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f"{name}: field {field!r} has {arr.shape[0]} rows, expected {n}")
        out[field] = arr
    return out


class SamplesWriter:
    """Append sample chunks, then :meth:`close` with the image keys and meta to write the npz.

    Usage::

        with SamplesWriter(path) as writer:
            for chunk in chunks:            # dicts with every field of SAMPLE_FIELDS
                writer.append(chunk)
            writer.finish(image_keys, meta)  # writes path atomically

    Memory is O(one chunk): rows go to temporary raw files beside ``path``.  Leaving the ``with``
    block without :meth:`finish` (e.g. on an exception) writes nothing and removes the spool.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._spool = Path(tempfile.mkdtemp(prefix=f".{self.path.stem}.", suffix=SPOOL_MARK, dir=self.path.parent))
        self._files = {f: open(self._spool / f"{f}.bin", "wb") for f in SAMPLE_FIELDS}
        self.count = 0

    def append(self, arrays: dict[str, Any]) -> int:
        """Append one chunk (dict field -> array with equal row counts); returns the total so far."""
        chunk = _check_chunk(arrays, str(self.path))
        for field, arr in chunk.items():
            self._files[field].write(arr.tobytes())
        self.count += len(chunk["image_id"])
        return self.count

    def finish(self, image_keys: Iterable[str], meta: dict) -> Path:
        """Assemble the npz (atomic rename) and return its path."""
        keys = np.asarray([str(k) for k in image_keys], dtype=str)
        if keys.ndim != 1:
            raise ValueError("image_keys must be a 1-D sequence of strings")
        for f in self._files.values():
            f.close()
        meta = {"schema": SCHEMA, **meta, "count": int(self.count), "image_count": int(len(keys))}
        meta_arr = np.asarray(json.dumps(json_ready(meta)))
        with atomic_path(self.path) as tmp:
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
                for field, (dtype, tail) in SAMPLE_FIELDS.items():
                    with zf.open(f"{field}.npy", "w", force_zip64=True) as member:
                        header = {
                            "descr": np.lib.format.dtype_to_descr(dtype),
                            "fortran_order": False,
                            "shape": (self.count, *tail),
                        }
                        np.lib.format.write_array_header_2_0(member, header)
                        with open(self._spool / f"{field}.bin", "rb") as src:
                            shutil.copyfileobj(src, member, _COPY_BLOCK)
                for name, arr in (("image_keys", keys), ("meta", meta_arr)):
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                        np.lib.format.write_array(member, arr, allow_pickle=False)
        self._cleanup()
        return self.path

    def _cleanup(self) -> None:
        for f in self._files.values():
            f.close()
        shutil.rmtree(self._spool, ignore_errors=True)

    def __enter__(self) -> "SamplesWriter":
        return self

    def __exit__(self, *exc) -> None:
        self._cleanup()


def write_samples(path: str | os.PathLike, arrays: dict[str, Any], meta: dict) -> Path:
    """Write all samples at once: ``arrays`` holds every field of SAMPLE_FIELDS plus ``image_keys``."""
    fields = {k: v for k, v in arrays.items() if k != "image_keys"}
    with SamplesWriter(path) as writer:
        writer.append(fields)
        return writer.finish(arrays["image_keys"], meta)


def _open_npz(path: Path):
    if not path.exists():
        raise UserError(f"{path}: samples file not found; run `sigrend samples` first")
    try:
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path}: not a readable samples.npz ({exc}); run `sigrend samples --force`") from None
    missing = [f for f in (*SAMPLE_FIELDS, "image_keys", "meta") if f not in npz.files]
    if missing:
        npz.close()
        raise UserError(
            f"{path}: samples file lacks field(s) {', '.join(missing)}; "
            "it was not written by `sigrend samples` (run it again with --force)"
        )
    return npz


def read_samples_meta(path: str | os.PathLike) -> dict:
    """The JSON meta of a samples file (plus ``image_keys`` as a list); reads no sample rows."""
    path = Path(path)
    with _open_npz(path) as npz:
        meta = json.loads(str(npz["meta"][()]))
        meta["image_keys"] = [str(k) for k in npz["image_keys"]]
    return meta


def read_samples(path: str | os.PathLike, fields: Iterable[str] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read a samples file whole: (arrays, meta).

    ``arrays`` has the requested ``fields`` (default: all of SAMPLE_FIELDS) and ``image_keys``
    ((M,) str); ``meta`` is the parsed JSON meta.  For large files prefer :func:`iter_sample_chunks`.
    """
    path = Path(path)
    fields = list(SAMPLE_FIELDS if fields is None else fields)
    unknown = [f for f in fields if f not in SAMPLE_FIELDS]
    if unknown:
        raise ValueError(f"unknown sample field(s) {unknown}; known: {list(SAMPLE_FIELDS)}")
    with _open_npz(path) as npz:
        arrays = {f: npz[f] for f in fields}
        arrays["image_keys"] = npz["image_keys"]
        meta = json.loads(str(npz["meta"][()]))
    return arrays, meta


def _member_memmap(path: Path, info: zipfile.ZipInfo) -> np.ndarray | None:
    """Memory-map a stored (uncompressed) .npy member of a ZIP; None if it is compressed."""
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)
        if local[:4] != b"PK\x03\x04":
            return None
        name_len, extra_len = struct.unpack("<HH", local[26:30])
        fh.seek(info.header_offset + 30 + name_len + extra_len)
        version = np.lib.format.read_magic(fh)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(fh)
        offset = fh.tell()
    if fortran or dtype.hasobject:
        return None
    if int(np.prod(shape)) == 0:
        return np.empty(shape, dtype=dtype)
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)


def iter_sample_chunks(
    path: str | os.PathLike, chunk: int = 1_000_000, fields: Iterable[str] | None = None
) -> Iterator[dict[str, np.ndarray]]:
    """Yield consecutive row chunks of the samples (dict field -> array of <= ``chunk`` rows).

    Members are memory-mapped, so memory is O(chunk x fields); each yielded array is an
    ordinary in-memory copy.  ``fields`` defaults to all of SAMPLE_FIELDS.
    """
    path = Path(path)
    fields = list(SAMPLE_FIELDS if fields is None else fields)
    unknown = [f for f in fields if f not in SAMPLE_FIELDS]
    if unknown:
        raise ValueError(f"unknown sample field(s) {unknown}; known: {list(SAMPLE_FIELDS)}")
    if chunk <= 0:
        raise ValueError("chunk must be positive")
    with _open_npz(path) as npz:
        sources = {}
        for f in fields:
            mapped = _member_memmap(path, npz.zip.getinfo(f"{f}.npy"))
            sources[f] = mapped if mapped is not None else npz[f]
    n = len(next(iter(sources.values()))) if sources else 0
    for start in range(0, n, chunk):
        yield {f: np.array(src[start : start + chunk]) for f, src in sources.items()}
