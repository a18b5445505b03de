"""samples.npz round trips: whole-file and chunked writes, whole-file and chunked (memory-mapped) reads."""

import zipfile

import numpy as np
import pytest

from pipeline.errors import UserError
from pipeline.io.samples import (
    SAMPLE_FIELDS,
    SCHEMA,
    SamplesWriter,
    iter_sample_chunks,
    read_samples,
    read_samples_meta,
    write_samples,
)


def random_samples(rng, n):
    out = {}
    for field, (dtype, tail) in SAMPLE_FIELDS.items():
        if dtype.kind == "f":
            out[field] = rng.standard_normal((n, *tail)).astype(dtype)
        else:
            out[field] = rng.integers(0, 1000, (n, *tail)).astype(dtype)
    return out


def test_round_trip_is_exact(tmp_path, rng):
    """samples.npz round-trips every field with its dtype exactly, with image keys and metadata; plain np.load
    reads it, and every member is stored uncompressed (memory-mappable)."""
    arrays = random_samples(rng, 101)
    arrays["image_keys"] = ["a.exr", "sub/b.exr"]
    write_samples(tmp_path / "s.npz", arrays, {"drops": {"background": 7}})
    got, meta = read_samples(tmp_path / "s.npz")
    for field in SAMPLE_FIELDS:
        assert got[field].dtype == SAMPLE_FIELDS[field][0]
        np.testing.assert_array_equal(got[field], arrays[field])
    assert list(got["image_keys"]) == ["a.exr", "sub/b.exr"]
    assert meta["schema"] == SCHEMA and meta["count"] == 101 and meta["image_count"] == 2
    assert meta["drops"] == {"background": 7}
    assert read_samples_meta(tmp_path / "s.npz")["image_keys"] == ["a.exr", "sub/b.exr"]
    # plain np.load reads it too, and every member is stored uncompressed (memory-mappable)
    with np.load(tmp_path / "s.npz") as npz:
        np.testing.assert_array_equal(npz["radiance"], arrays["radiance"])
    with zipfile.ZipFile(tmp_path / "s.npz") as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}


@pytest.mark.parametrize("chunk", [1, 7, 50, 1000])
def test_chunked_write_and_read_match_whole(tmp_path, rng, chunk):
    """Writing in parts (an empty one included) and reading in chunks of 1 to 1000 rows gives the whole arrays
    back, in chunks of the asked size."""
    parts = [random_samples(rng, n) for n in (13, 0, 30, 1)]
    with SamplesWriter(tmp_path / "s.npz") as writer:
        for part in parts:
            writer.append(part)
        writer.finish(["k"], {})
    whole = {f: np.concatenate([p[f] for p in parts]) for f in SAMPLE_FIELDS}
    chunks = list(iter_sample_chunks(tmp_path / "s.npz", chunk=chunk, fields=["point", "image_id"]))
    assert [len(c["point"]) for c in chunks] == [min(chunk, 44 - s) for s in range(0, 44, chunk)]
    np.testing.assert_array_equal(np.concatenate([c["point"] for c in chunks]), whole["point"])
    np.testing.assert_array_equal(np.concatenate([c["image_id"] for c in chunks]), whole["image_id"])


def test_compressed_npz_from_numpy_is_read_in_chunks_too(tmp_path, rng):
    """A compressed npz written by NumPy itself is read in chunks as well."""
    arrays = random_samples(rng, 9)
    np.savez_compressed(tmp_path / "c.npz", **arrays, image_keys=np.array(["x"]), meta=np.array("{}"))
    chunks = list(iter_sample_chunks(tmp_path / "c.npz", chunk=4, fields=["bary"]))
    np.testing.assert_array_equal(np.concatenate([c["bary"] for c in chunks]), arrays["bary"])


def test_failed_write_leaves_nothing(tmp_path, rng):
    """A write interrupted by an exception leaves no file behind."""
    with pytest.raises(RuntimeError):
        with SamplesWriter(tmp_path / "s.npz") as writer:
            writer.append(random_samples(rng, 3))
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_bad_chunks_and_files(tmp_path, rng):
    """A chunk whose fields disagree in length is refused naming the field; a missing file and an npz without the
    samples' fields are UserErrors."""
    bad = random_samples(rng, 3)
    bad["normal"] = bad["normal"][:2]
    with SamplesWriter(tmp_path / "s.npz") as writer, pytest.raises(ValueError, match="normal"):
        writer.append(bad)
    with pytest.raises(UserError, match="not found"):
        read_samples(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(UserError, match="lacks field"):
        read_samples_meta(tmp_path / "other.npz")
