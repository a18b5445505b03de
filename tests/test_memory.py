"""The memory budget (--memory-limit, pipeline.memory): sizes as people type them, a capture of large
photos linearized and sampled within a budget that the photos decoded whole would exceed (peak RSS
of the stage's process, measured by a parent process of its own), and a budget that cannot be met
stopping with one line that says what to reduce, the earlier outputs untouched."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from helpers import assert_one_line_error

from pipeline.core.camera import Camera, Rigid3, look_at
from pipeline.errors import UserError
from pipeline.io.images import write_image
from pipeline.io.poses import ImagePose, Poses, write_poses
from pipeline.memory import Budget, band_rows, machine_memory, parse_size

WIDTH, HEIGHT = 6000, 4000  # 24 MP
LIMIT = "600MB"
# the parent: runs the command and prints the largest RSS of its children (the stage, serial) in bytes
PEAK = (
    "import resource, subprocess, sys; code = subprocess.run(sys.argv[1:]).returncode; "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, code)"
)


def test_sizes_are_parsed_as_people_type_them():
    """Decimal and binary units, a bare number of bytes and a share of the machine's RAM; anything
    else is a UserError naming the option and showing what to type."""
    assert parse_size("8GB") == 8 * 10**9 and parse_size("8G") == 8 * 10**9
    assert parse_size("16GiB") == 16 * 2**30 and parse_size("512MB") == 512 * 10**6
    assert parse_size("1.5e9") == 1_500_000_000
    assert parse_size("50%") == machine_memory() // 2 or abs(parse_size("50%") - machine_memory() / 2) <= 1
    for bad in ("8 gigs", "-1GB", "0", "150%", ""):
        with pytest.raises(UserError, match="--memory-limit"):
            parse_size(bad)
    assert Budget.of("1GB").workers(8, 300 * 10**6, processes=False) <= 3
    assert band_rows(6000, 100, 60 * 10**6, 4000) == 100 and band_rows(6000, 100, 10, 4000) == 16


@pytest.fixture(scope="module")
def large_capture(tmp_path_factory):
    """Two 24 MP JPEGs (a smooth sphere-like disc on a gradient, EXIF exposure) of an icosphere, posed."""
    root = tmp_path_factory.mktemp("large") / "capture"
    (root / "images").mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=4, radius=0.1).export(root / "mesh.ply")
    focal = 1.2 * WIDTH
    camera = Camera("PINHOLE", WIDTH, HEIGHT, (focal, focal, WIDTH / 2, HEIGHT / 2))
    poses = Poses(cameras={"cam0": camera})
    y, x = np.ogrid[0:HEIGHT, 0:WIDTH]
    r2 = ((x - WIDTH / 2) ** 2 + (y - HEIGHT / 2) ** 2) / (0.3 * HEIGHT) ** 2
    for i, centre in enumerate([(0.5, 0.0, 0.1), (0.0, 0.5, -0.1)]):
        R, t = look_at(centre, (0.0, 0.0, 0.0))
        poses.images[f"{i}.jpg"] = ImagePose("cam0", Rigid3(R, t))
        value = np.where(r2 < 1, 0.8 * np.sqrt(np.clip(1 - r2, 0, 1)), 0.1 + 0.2 * x / WIDTH).astype(np.float32)
        write_image(
            root / "images" / f"{i}.jpg",
            np.repeat(value[:, :, None], 3, axis=2) * [1.0, 0.8, 0.6],
            dtype="uint8",
            attributes={"ExposureTime": 0.01, "FNumber": 4.0, "Exif:PhotographicSensitivity": 100, "Compression": "jpeg:90"},
        )
    write_poses(root / "poses.json", poses)
    return root


def peak_rss(*args: str) -> tuple[int, int]:
    """(peak RSS in bytes, exit code) of `sigrend ARGS` run by a fresh parent process."""
    out = subprocess.run(
        [sys.executable, "-c", PEAK, sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True, check=True
    ).stdout.split()
    return int(out[-2]), int(out[-1])


@pytest.fixture(scope="module")
def linearized(large_capture, tmp_path_factory):
    """The large capture linearized under the budget, serially (the stage's own process): (work, peak RSS)."""
    work = tmp_path_factory.mktemp("linearized") / "work"
    peak, code = peak_rss("linearize", str(large_capture), "-w", str(work), "--workers", "1", "--memory-limit", LIMIT)
    assert code == 0
    return work, peak


@pytest.mark.slow  # 20-35 s with its fixtures: 24 MP photos decoded in subprocesses
def test_large_photos_are_linearized_and_sampled_within_the_budget(large_capture, linearized, tmp_path):
    """Two 24 MP photos decoded whole as float RGB (the stages' in-memory path) would be 576 MB of
    pixels alone, beyond the 600 MB budget beside the process's own ~0.1-0.2 GB; streamed in bands
    of rows, linearize (serial, in the stage's own process) and samples (its threads as the budget
    allows) each peak below it, and the outputs cover every pixel."""
    limit = parse_size(LIMIT)
    assert 2 * WIDTH * HEIGHT * 3 * 4 > 0.9 * limit  # the capture is made to exceed the budget whole
    work, peak = linearized
    assert peak < limit, peak
    manifest = json.loads((work / "linear" / "manifest.json").read_text())
    assert [manifest["images"][k]["width"] * manifest["images"][k]["height"] for k in ("0", "1")] == [WIDTH * HEIGHT] * 2
    shutil.copytree(work, tmp_path / "work")
    work = tmp_path / "work"
    peak, code = peak_rss("samples", str(large_capture), "-w", str(work), "--stride", "4", "--memory-limit", LIMIT)
    assert code == 0 and peak < limit, peak
    summary = json.loads((work / "samples_summary.json").read_text())
    assert summary["pixels"] == 2 * (WIDTH // 4) * (HEIGHT // 4) and summary["count"] > 10**5


@pytest.mark.slow  # 10-17 s: subprocesses on the 24 MP capture
def test_a_budget_that_cannot_be_met_is_one_line(large_capture, linearized, tmp_path):
    """A budget below what one photo's chunk needs: exit 2, one line naming the limit and what to
    reduce (samples: --chunk-pixels; linearize: the photos' size), no traceback, and the outputs
    of the earlier stages byte-identical."""
    shutil.copytree(linearized[0], tmp_path / "work")
    work = tmp_path / "work"
    sigrend = [sys.executable, "-m", "pipeline.cli"]
    subprocess.run([*sigrend, "samples", str(large_capture), "-w", str(work), "--stride", "8"], check=True, capture_output=True)
    digests = {p: hashlib.md5(p.read_bytes()).hexdigest() for p in [work / "samples.npz", *work.glob("linear/*")] if p.is_file()}
    result = subprocess.run(
        [
            *sigrend,
            "samples",
            str(large_capture),
            "-w",
            str(work),
            "--stride",
            "8",
            "--memory-limit",
            "2GB",
            "--chunk-pixels",
            "24000000",
        ],
        capture_output=True,
        text=True,
    )
    assert_one_line_error(result, "--memory-limit 2GB", "lower --chunk-pixels", progress=True)
    result = subprocess.run(
        [*sigrend, "linearize", str(large_capture), "-w", str(work), "--force", "--memory-limit", "50MB"],
        capture_output=True,
        text=True,
    )
    assert_one_line_error(result, "--memory-limit 50MB", "0.jpg", "24 MP", "use smaller photos", progress=True)
    assert {p: hashlib.md5(p.read_bytes()).hexdigest() for p in digests} == digests


def test_the_fit_holds_as_many_of_every_sample_as_its_budget_allows(tmp_path):
    """The fit's every-sample steps (texels, the material map) hold EVERY_SAMPLE_BYTES per sample in
    EVERY_SAMPLE_SHARE of --memory-limit (stages.fit.data.every_sample_cap): 200 000 samples under 200 MB
    (room for 142 857) are a random share of 71.4 % (binomial: kept within 1 %), the subset still
    --physical-samples and its reason stated; under 1 GB all of them, no reason; under 16 MB not even
    the subset fits: one line naming the limit and what to lower."""
    from pipeline.io.samples import write_samples
    from stages.fit.data import EVERY_SAMPLE_BYTES, EVERY_SAMPLE_SHARE, every_sample_cap, load_physical
    from stages.fit.settings import Settings

    n, rng = 200_000, np.random.default_rng(0)
    bary = rng.dirichlet([1.0, 1.0, 1.0], n)
    arrays = {
        "point": np.zeros((n, 3)),
        "normal": np.tile([0.0, 0.0, 1.0], (n, 1)),
        "view_dir": np.tile([0.0, 0.0, 1.0], (n, 1)),
        "radiance": rng.uniform(0.2, 0.8, (n, 3)),
        "image_id": rng.integers(0, 4, n),
        "pixel": rng.uniform(0, 100, (n, 2)),
        "face": rng.integers(0, 10, n),
        "bary": bary,
        "weight": np.ones(n),
        "visibility": np.ones(n),
        "image_keys": ["a", "b", "c", "d"],
    }
    path = write_samples(tmp_path / "samples.npz", arrays, {})
    share, note = every_sample_cap(path, Settings(memory_limit="200MB"))
    most = int(EVERY_SAMPLE_SHARE * 200e6 // EVERY_SAMPLE_BYTES)
    assert share == pytest.approx(most / n) and share < 1.0 and "--memory-limit 200MB" in note["why"]
    data, _, everything = load_physical(path, Settings(memory_limit="200MB"), 10, share)
    assert len(everything["weight"]) == pytest.approx(share * n, rel=0.01)
    assert len(data["weight"]) == Settings().physical_samples
    share, note = every_sample_cap(path, Settings(memory_limit="1GB"))
    assert share == 1.0 and "why" not in note
    with pytest.raises(UserError, match=r"--memory-limit 16MB .*lower --physical-samples"):
        every_sample_cap(path, Settings(memory_limit="16MB"))
