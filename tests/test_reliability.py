"""A stage's outputs are committed together, last (issue 17): a stage killed (SIGKILL, by its own
pid, at a chosen output) or failing half-way leaves the previous outputs byte-identical and the
next run trusts only a complete set.  The fault injector runs the real CLI in a subprocess whose
``atomic_path`` kills the process right after the chosen file's n-th write."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error

from pipeline import cli
from pipeline.core.brdf import Brdf
from pipeline.io.images import read_image
from pipeline.workdir import LOCK_NAME

ROOT = Path(__file__).parents[1]

KILLER = r"""
import contextlib, os, signal, sys
from pathlib import Path
import pipeline.workdir as workdir            # patched before any module imports atomic_path
target, count, argv = sys.argv[1], int(sys.argv[2]), sys.argv[4:]
sig = getattr(signal, sys.argv[3])
original, seen = workdir.atomic_path, []

@contextlib.contextmanager
def atomic_path(path):
    with original(path) as tmp:
        yield tmp
    if Path(path).name == target:
        seen.append(path)
        if len(seen) >= count:
            os.kill(os.getpid(), sig)

workdir.atomic_path = atomic_path
from pipeline import cli
sys.exit(cli.main(argv))
"""

pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning")


def kill_at(target: str, count: int, *argv: str, sig: str = "SIGKILL") -> subprocess.CompletedProcess:
    """Run ``sigrend ARGV`` in a subprocess that sends itself ``sig`` after its ``count``-th write
    of a file named ``target`` (returncode -9 when SIGKILL happened)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-c", KILLER, target, str(count), sig, *map(str, argv)], env=env, capture_output=True, text=True
    )


def digest(folder: Path) -> dict[str, str]:
    """sha256 of every file in ``folder`` but the lock (it names its last holder's pid)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != LOCK_NAME
    }


@pytest.fixture
def linearized(tiny_capture, tmp_path):
    capture = tiny_capture(views=6, size=(48, 48))
    work = tmp_path / "work"
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    return capture, work


def test_a_killed_rerun_with_other_settings_leaves_the_outputs_byte_identical(linearized, capsys):
    """linearize SIGKILLed half-way through a rerun with other settings leaves the committed outputs byte-
    identical (only its temporaries behind); the old set is still fresh for its settings, the new settings run
    again, and the stale temporaries are removed."""
    capture, work = linearized
    before = digest(work)
    # killed after the third mask of a re-run with other settings: nothing of it is committed
    code = kill_at("0002.png", 1, "linearize", capture, "-w", work, "--saturation", "0.6", "--workers", "1").returncode
    assert code == -signal.SIGKILL
    leftovers = [p for p in work.rglob("*") if p.is_file() and ".tmp" in p.name]
    assert leftovers, "the killed process should have left its uncommitted temporaries"
    assert {k: v for k, v in digest(work).items() if ".tmp" not in k} == before
    # the old set is complete and fresh for its own settings; the new settings run again
    capsys.readouterr()
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    assert "fresh, skipped" in capsys.readouterr().out
    assert cli.main(["linearize", str(capture), "-w", str(work), "--saturation", "0.6"]) == 0
    assert "fresh, skipped" not in capsys.readouterr().out
    assert not [p for p in work.rglob("*") if ".tmp" in p.name]  # stale temporaries removed at the start
    assert digest(work) != before


def test_worker_processes_commit_with_the_stage(linearized):
    """Images linearized in worker processes are handed to the stage's commit: killed after the
    manifest (the parent's last write, when every worker has finished), nothing has changed."""
    capture, work = linearized
    before = digest(work)
    assert (
        kill_at("manifest.json", 1, "linearize", capture, "-w", work, "--saturation", "0.6", "--workers", "2").returncode
        == -signal.SIGKILL
    )
    assert {k: v for k, v in digest(work).items() if ".tmp" not in k} == before


def test_a_killed_samples_run_leaves_no_spool_behind(linearized):
    """samples.npz streams its rows through a spool folder beside it: killed right after the npz is
    written (before the spool is removed), the folder stays; the next stage start removes it."""
    capture, work = linearized
    assert kill_at("samples.npz", 1, "samples", capture, "-w", work).returncode == -signal.SIGKILL
    assert list(work.glob(".samples.*.spool")), "the killed process should have left its spool"
    assert cli.main(["samples", str(capture), "-w", str(work)]) == 0
    assert not list(work.glob(".samples.*.spool")) and not [p for p in work.rglob("*") if ".tmp" in p.name]


def _process_states() -> dict[int, tuple[str, int]]:
    """pid -> (state, parent pid) of every process, from /proc."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended while we read
            continue
        out[int(stat.parent.name)] = (fields[0], int(fields[1]))
    return out


def _descendants(pid: int) -> set[int]:
    """Processes below ``pid``."""
    parents = {p: parent for p, (_, parent) in _process_states().items()}
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _running(pids: set[int]) -> set[int]:
    """Those of ``pids`` that still run (zombies do not)."""
    states = _process_states()
    return {p for p in pids if p in states and states[p][0] != "Z"}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc; PR_SET_PDEATHSIG is Linux's")
def test_worker_processes_die_with_a_killed_stage(tmp_path):
    """kill -9 of `sigrend linearize --workers 2` while its workers are busy: every process it
    started (the forkserver, its resource tracker and the pool's workers) is gone within 10 s."""
    import time

    import cv2

    images = tmp_path / "capture" / "images"
    images.mkdir(parents=True)
    photo = np.random.default_rng(0).integers(0, 256, (1200, 1600, 3), dtype=np.uint8)
    for i in range(60):
        cv2.imwrite(str(images / f"{i:03d}.jpg"), np.roll(photo, i, axis=1))
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "linearize",
            str(tmp_path / "capture"),
            "-w",
            str(tmp_path / "work"),
            "--workers",
            "2",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    started, deadline = set(), time.monotonic() + 60
    while len(started) < 3 and proc.poll() is None and time.monotonic() < deadline:  # forkserver + 2 workers
        started = _descendants(proc.pid)
        time.sleep(0.05)
    assert len(started) >= 3 and proc.poll() is None, "the stage ended before its workers could be seen"
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    while _running(started) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = _running(started)
    assert not left, f"processes of the killed stage still running: {sorted(left)}"


def test_sigterm_is_handled_as_an_interrupt(linearized):
    """SIGTERM mid-stage: one line, exit 128 + 15, the transaction rolled back (no temporaries)."""
    capture, work = linearized
    before = digest(work)
    result = kill_at("0002.png", 1, "linearize", capture, "-w", work, "--saturation", "0.6", "--workers", "1", sig="SIGTERM")
    assert result.returncode == 128 + signal.SIGTERM, result.stderr
    lines = [line for line in result.stderr.strip().splitlines() if line.startswith("sigrend:")]
    assert lines == ["sigrend: terminated; finished outputs are kept, run again to resume"], result.stderr
    assert "Traceback" not in result.stderr
    assert digest(work) == before


def test_a_closed_stdout_ends_quietly(linearized):
    """`sigrend ... | head -0`: the reader is gone before the stage prints its outputs."""
    capture, work = linearized
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    read, write = os.pipe()
    os.close(read)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "pipeline.cli", "linearize", str(capture), "-w", str(work)],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
    finally:
        os.close(write)
    assert result.returncode == 0 and result.stderr == "", result.stderr


def _user_error(path):
    from pipeline.errors import UserError

    return UserError("injected failure after two images")


def _disk_full(path):
    import errno

    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


# a stage failing half-way: a user error, or the machine's (a full disk: one line naming the file, no
# traceback) -> a fragment of the one-line message; either way nothing of the stage is committed
@pytest.mark.parametrize(
    "fault, fragment",
    [
        (_user_error, "injected failure after two images"),
        (_disk_full, "No space left on device; free some space or give -w a folder on another disk"),
    ],
)
def test_a_stage_that_fails_half_way_commits_nothing(linearized, monkeypatch, capsys, fault, fragment):
    """A stage failing at its third image (a user error, or a full disk) is one line with the expected message,
    and the two images it wrote before are not committed: the work folder is byte-identical."""
    from stages.linearize import jobs

    capture, work = linearized
    before = digest(work)
    real = jobs.ImageRowWriter  # each photo's mask and EXR are written through one of these (linearize_job)
    calls = []

    def failing(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 3:
            raise fault(path)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(jobs, "ImageRowWriter", failing)
    capsys.readouterr()
    assert cli.main(["linearize", str(capture), "-w", str(work), "--saturation", "0.6", "--workers", "1"]) == 2
    assert len(calls) == 3
    assert_one_line_error(capsys.readouterr().err, fragment)
    assert digest(work) == before  # the two images written before the failure were not committed


def test_freshness_is_by_content_not_file_times(tiny_capture, tmp_path, capsys):
    """A photo replaced by another with an older time (cp -p, rsync -a, unzip) is noticed: its
    linear image is redone and the stages after it are not trusted; a removed photo too."""
    source = tiny_capture(views=6, size=(48, 48))
    capture = tmp_path / "capture"
    shutil.copytree(source, capture)
    work = tmp_path / "work"
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    before = digest(work / "linear")
    pixels_2 = read_image(work / "linear" / "0002.exr")
    capsys.readouterr()
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    assert "fresh, skipped" in capsys.readouterr().out
    # swap two photos' contents and set their times back by a day
    a, b = capture / "images" / "0001.exr", capture / "images" / "0002.exr"
    old = a.stat().st_mtime - 86400
    data_a, data_b = a.read_bytes(), b.read_bytes()
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    for p in (a, b):
        os.utime(p, (old, old))
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    assert "fresh, skipped" not in capsys.readouterr().out
    after = digest(work / "linear")
    assert after["0000.exr"] == before["0000.exr"]  # the others were not redone
    assert after["0001.exr"] != before["0001.exr"] and after["0002.exr"] != before["0002.exr"]
    assert np.array_equal(read_image(work / "linear" / "0001.exr"), pixels_2)  # the swapped content
    # a removed photo changes the stage's input set
    (capture / "images" / "0005.exr").unlink()
    assert cli.main(["linearize", str(capture), "-w", str(work)]) == 0
    assert "fresh, skipped" not in capsys.readouterr().out
    manifest = json.loads((work / "linear" / "manifest.json").read_text())
    assert sorted(manifest["images"]) == ["0000", "0001", "0002", "0003", "0004"]
    assert not (work / "linear" / "0005.exr").exists() and not (work / "linear" / "masks" / "0005.png").exists()


# bad capture.toml content -> (its text, a fragment of the one-line message); a new case is one line
BAD_CAPTURE_TOML = {
    "misspelt section": ("[exposre]\ndefault = {iso = 100}\n", "unknown [exposre] (did you mean 'exposure'?)"),
    "misspelt key": ("[white_balance]\nmultiplier = [2, 1, 1.5]\n", "[white_balance] multiplier (did you mean 'multipliers'?)"),
    "top-level value": ('white_balance = "daylight"\n', "white_balance = ... must be a [white_balance] table"),
    "section glued": ("[whitebalance]\nmultipliers = [2, 1, 1.5]\n", "(did you mean 'white_balance'?)"),
    "exposure of no file": (
        '[exposure]\n"0001.ex" = {iso = 200}\n"IMG_9.jpg" = {iso = 200}\n',
        "[exposure] names no image of the capture: '0001.ex' (did you mean '0001.exr'?), 'IMG_9.jpg'",
    ),
    "board transform as a word": (
        '[board]\ndictionary = "DICT_5X5_100"\nsquares = [8, 6]\nsquare_length = 0.07\n'
        'marker_length = 0.0525\nboard_to_object = "identity"\n',
        "board_to_object must be a finite 4x4 matrix of numbers",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CAPTURE_TOML))
def test_bad_capture_toml_is_one_line_naming_the_key(tiny_capture, tmp_path, capsys, case):
    """Each bad capture.toml is one line naming the section or key at fault, and linearize writes nothing."""
    text, fragment = BAD_CAPTURE_TOML[case]
    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    (capture / "capture.toml").write_text(text)
    capsys.readouterr()
    assert cli.main(["linearize", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, fragment)
    assert not (tmp_path / "work" / "linear").exists()


def test_two_meshes_are_an_error_not_a_guess(tiny_capture, tmp_path, capsys):
    """A capture with both mesh.ply and mesh.obj is one line saying both are there, not a guess at which is the
    object."""
    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    shutil.copy(capture / "mesh.ply", capture / "mesh.obj")
    capsys.readouterr()
    assert cli.main(["samples", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, "mesh.ply and mesh.obj are both there")


def test_a_truncated_jpeg_is_an_error_not_grey_pixels(tmp_path):
    """libjpeg decodes the first half of a truncated JPEG and fills the rest with grey, a "valid"
    image; OpenImageIO's error flag makes it one line naming the file."""
    import cv2

    from pipeline.errors import UserError

    image = (np.random.default_rng(0).random((128, 128, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "full.jpg"), image)
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    assert read_image(tmp_path / "full.jpg").shape == (128, 128, 3)
    with pytest.raises(UserError, match="cut.jpg: the decoder reported .*Premature end of JPEG file"):
        read_image(tmp_path / "cut.jpg")


def _with_mesh(tiny_capture, tmp_path, edit) -> Path:
    """A copy of a tiny capture whose (closed) sphere mesh has faces edited by ``edit(faces)``."""
    import trimesh

    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    mesh = trimesh.load(capture / "mesh.ply", process=False)
    trimesh.Trimesh(mesh.vertices, edit(np.asarray(mesh.faces).copy()), process=False).export(capture / "mesh.ply")
    return capture


@pytest.mark.parametrize(
    "edit, fragment",
    [
        (lambda f: np.concatenate([f[:40, ::-1], f[40:]]), "edges join faces wound in opposite directions"),
        (lambda f: f[:, ::-1], "the mesh is inside out"),
    ],
)
def test_a_mesh_with_flipped_faces_is_an_error_naming_the_fix(tiny_capture, tmp_path, capsys, edit, fragment):
    """A mesh with flipped faces or inside out is one line naming the fault and Blender's fix (Recalculate
    Outside), and no samples are written."""
    capture = _with_mesh(tiny_capture, tmp_path, edit)
    capsys.readouterr()
    assert cli.main(["samples", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, fragment, "Recalculate Outside")
    assert not (tmp_path / "work" / "samples.npz").exists()


def test_a_mesh_with_holes_is_sampled_with_a_warning_and_counted(tiny_capture, tmp_path):
    """An open mesh is sampled with a warning counting its boundary edges, recorded in samples_summary.json's
    mesh_quality (no inconsistent edges, not inside out)."""
    capture = _with_mesh(tiny_capture, tmp_path, lambda f: f[12:])
    with pytest.warns(UserWarning, match=r"mesh.ply: \d+ boundary edges \(holes"):
        assert cli.main(["samples", str(capture), "-w", str(tmp_path / "work")]) == 0
    quality = json.loads((tmp_path / "work" / "samples_summary.json").read_text())["mesh_quality"]
    assert quality["boundary_edges"] > 0 and quality["inconsistent_edges"] == 0 and not quality["inside_out"]


def test_a_second_run_on_a_busy_work_folder_says_so(linearized, capsys):
    """Two sigrends on one work folder would interleave their commits and clean each other's
    temporaries: the second one is refused while the first holds WORK/.sigrend.lock (flock: a
    killed holder releases it, so it is never stale)."""
    capture, work = linearized
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pipeline.workdir import work_lock\n"
            "with work_lock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)",
            str(work),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        capsys.readouterr()
        assert cli.main(["linearize", str(capture), "-w", str(work), "--force"]) == 2
        assert_one_line_error(capsys.readouterr().err, f"in use by sigrend pid {holder.pid}")
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    assert cli.main(["linearize", str(capture), "-w", str(work), "--force"]) == 0  # released with its holder


def _poses_cameras_as_list(doc):
    doc["cameras"] = list(doc["cameras"].values())


def _poses_camera_as_list(doc):
    first = sorted(doc["images"])[0]
    doc["images"][first]["camera"] = [doc["images"][first]["camera"]]


@pytest.mark.parametrize(
    "edit, fragment",
    [
        (_poses_cameras_as_list, "'cameras' must be an object mapping camera name"),
        (_poses_camera_as_list, "names unknown camera ['cam0']"),
    ],
)
def test_malformed_poses_json_is_one_line(tiny_capture, tmp_path, capsys, edit, fragment):
    """Each malformed poses.json value is one line naming it."""
    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    doc = json.loads((capture / "poses.json").read_text())
    edit(doc)
    (capture / "poses.json").write_text(json.dumps(doc))
    capsys.readouterr()
    assert cli.main(["samples", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, fragment)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["linearize", "{capture}", "-w", "{file}"], "this is a file, not a folder; give -w a folder path"),
        (["run", "{capture}", "-w", "{file}/work", "--no-report"], "cannot create this folder (Not a directory)"),
        (["relight", "{capture}", "-w", "{work}", "-o", "{file}"], "give -o a folder path"),
    ],
)
def test_an_output_path_that_is_a_file_is_one_line(linearized, tmp_path, capsys, args, fragment):
    """A -w or -o that is an existing file (or under one) is one line saying to give a folder, and the file is kept."""
    from pipeline.io.brdf import write_brdf
    from pipeline.io.lighting import write_lighting_sh

    capture, work = linearized
    write_brdf(work / "fit" / "brdf.json", Brdf("lambert", albedo=[0.5, 0.5, 0.5]))  # what relight reads
    write_lighting_sh(work / "fit" / "lighting_sh.json", np.ones((1, 3)))
    (tmp_path / "afile").write_text("not a folder")
    argv = [a.format(capture=capture, work=work, file=tmp_path / "afile") for a in args]
    capsys.readouterr()
    assert cli.main(argv) == 2
    assert_one_line_error(capsys.readouterr().err, fragment)
    assert (tmp_path / "afile").read_text() == "not a folder"


# a wrong type or value in a JSON file the stages read -> (file, its edit, a fragment of the one-line
# message); every reader type-checks (pipeline.io.values): a number is never a string or a bool
def _set(*path_and_value):
    *path, value = path_and_value

    def edit(doc):
        target = doc
        for key in path[:-1]:
            target = target[key] if not callable(key) else key(target)
        target[path[-1]] = value

    return edit


def _first_image(doc):
    return doc["images"][sorted(doc["images"])[0]]


BAD_JSON_VALUES = {
    "camera width as a string": (
        "poses.json",
        _set("cameras", "cam0", "width", "48"),
        "width and height must be positive whole numbers of pixels, got '48'",
    ),
    "camera width infinite": (
        "poses.json",
        _set("cameras", "cam0", "width", float("inf")),
        "width and height must be positive whole numbers",
    ),
    "camera model as a list": ("poses.json", _set("cameras", "cam0", "model", []), "has unsupported model []"),
    "camera params as numbers in strings": (
        "poses.json",
        _set("cameras", "cam0", "params", ["64", "64", "24", "24"]),
        "(PINHOLE) needs params: a list of 4 numbers",
    ),
    "negative focal length": (
        "poses.json",
        _set("cameras", "cam0", "params", [-64.0, 64.0, 24.0, 24.0]),
        "the focal length must be positive",
    ),
    "rotation of strings": ("poses.json", _set(_first_image, "R", "identity"), "needs camera, R (3x3), t (3)"),
    "brdf albedo as a word": ("fit/brdf.json", _set("albedo", "grey"), "albedo must be one or three non-negative numbers"),
    "brdf albedo as booleans": (
        "fit/brdf.json",
        _set("albedo", [True, True, True]),
        "albedo must be one or three non-negative numbers",
    ),
    "brdf model as a list": ("fit/brdf.json", _set("model", ["lambert"]), "unknown BRDF model ['lambert']"),
    "lighting order infinite": ("fit/lighting_sh.json", _set("order", float("inf")), "'order' must be a whole number"),
    "lighting coefficients ragged": (
        "fit/lighting_sh.json",
        _set("coeffs", [[1, 1, 1], [1]]),
        "'coeffs' must be (order+1)^2 rows of [r, g, b] numbers",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_JSON_VALUES))
def test_a_wrong_type_in_a_json_file_is_one_line(linearized, tmp_path, capsys, case):
    """A value of the wrong type in poses.json or fit/brdf.json is one line naming the value, from the stage
    that reads the file."""
    from pipeline.io.brdf import write_brdf
    from pipeline.io.lighting import write_lighting_sh

    rel, edit, fragment = BAD_JSON_VALUES[case]
    capture, work = linearized
    capture = shutil.copytree(capture, tmp_path / "capture")
    write_brdf(work / "fit" / "brdf.json", Brdf("lambert", albedo=[0.5, 0.5, 0.5]))
    write_lighting_sh(work / "fit" / "lighting_sh.json", np.ones((1, 3)))
    path = (capture if rel == "poses.json" else work) / rel
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    argv = (
        ["samples", str(capture), "-w", str(work)]
        if rel == "poses.json"
        else ["relight", str(capture), "-w", str(work), "-o", str(tmp_path / "out")]
    )
    capsys.readouterr()
    assert cli.main(argv) == 2
    assert_one_line_error(capsys.readouterr().err, fragment)


def test_warnings_wait_until_the_command_succeeds(tiny_capture, tmp_path, capsys):
    """A warning issued before a user error does not precede the error line (issue 17, point 4):
    no EXIF exposure warns (shown when linearize succeeds), then a grey patch outside the image fails."""
    import warnings

    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        assert cli.main(["linearize", str(capture), "-w", str(tmp_path / "work")]) == 0
    assert any("in any image's EXIF" in str(w.message) for w in shown)
    (capture / "capture.toml").write_text("[white_balance]\ngray_patch = [0, 0, 1000, 1000]\n")
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        assert cli.main(["linearize", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, "lies outside the 48x48 image")
    assert not shown  # held back, then dropped with the failed command


def test_force_redoes_every_linear_image(linearized):
    """--force redoes what it says, even images whose EXR records the same recipe (a hand-edited
    or damaged EXR is otherwise reused: its header still matches)."""
    capture, work = linearized
    exr = work / "linear" / "0000.exr"
    before = exr.stat()
    assert cli.main(["linearize", str(capture), "-w", str(work), "--force"]) == 0
    after = exr.stat()
    assert (after.st_ino, after.st_mtime_ns) != (before.st_ino, before.st_mtime_ns)


def test_an_all_transparent_exr_is_named_transparent_not_black(tiny_capture, tmp_path, capsys):
    """An EXR whose alpha is 0 everywhere is one line saying every pixel is transparent, not that the photo is
    black."""
    from pipeline.io.images import read_image, write_image

    capture = shutil.copytree(tiny_capture(views=6, size=(48, 48)), tmp_path / "capture")
    rgb = read_image(capture / "images" / "0002.exr")[:, :, :3]
    write_image(capture / "images" / "0002.exr", np.dstack([rgb, np.zeros(rgb.shape[:2], np.float32)]))
    capsys.readouterr()
    assert cli.main(["linearize", str(capture), "-w", str(tmp_path / "work")]) == 2
    assert_one_line_error(capsys.readouterr().err, "0002.exr: every pixel is transparent (alpha = 0)")
