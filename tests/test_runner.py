"""`sigrend run`: stage order, skip-if-fresh across runs, --from/--to, --force, held-out views and
a failing stage that leaves the earlier outputs intact.  Runs the real stages up to samples on a
tiny synthetic EXR capture that brings its own poses.json (no COLMAP).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import assert_one_line_error

from pipeline import STAGES, cli
from pipeline.io.run_summary import StageResult, stage_table
from pipeline.io.samples import read_samples_meta
from pipeline.runner import heldout_keys

# linear EXR renders carry no EXIF: linearize warns once per run and assumes equal exposure
pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning")


@pytest.fixture
def capture(tiny_capture) -> Path:
    return tiny_capture(views=8, size=(48, 48))


def _mtimes(work: Path, names: list[str]) -> dict[str, int]:
    return {n: (work / n).stat().st_mtime_ns for n in names}


STAGE_FILES = ["linear/manifest.json", "poses.json", "samples.npz"]


def _run(*args: str) -> int:
    return cli.main(["run", *map(str, args), "--no-report"])


def test_heldout_keys_every_fourth():
    """Every fourth view is held out (0003, 0007 of ten), none with a stride of 0, and none when fewer than two
    views per held-out one would remain."""
    keys = [f"{i:04d}.exr" for i in range(10)]
    assert heldout_keys(keys, 4) == ["0003.exr", "0007.exr"]
    assert heldout_keys(keys, 0) == []
    assert heldout_keys(keys[:5], 4) == []  # fewer than two per held-out view: keep all for the fit


def test_resume_skips_fresh_stages_and_force_redoes(capture, tmp_path, capsys):
    """A run holds out every fourth view; a second run finds every stage fresh and rewrites nothing; --from
    samples --force redoes samples alone, and --force over the range redoes every stage."""
    work = tmp_path / "work"
    assert _run(capture, "-w", work, "--to", "samples") == 0
    run = json.loads((work / "run.json").read_text())
    assert [s["name"] for s in run["stages"]] == ["linearize", "poses", "samples"]
    assert not any(s["skipped"] for s in run["stages"])
    # every 4th view is held out of the samples (8 views: the 4th and the 8th)
    assert read_samples_meta(work / "samples.npz")["holdout"] == ["0003.exr", "0007.exr"]
    before = _mtimes(work, STAGE_FILES)
    # as if killed after samples: the next run finds every stage fresh and redoes nothing
    assert _run(capture, "-w", work, "--to", "samples") == 0
    run = json.loads((work / "run.json").read_text())
    assert all(s["skipped"] for s in run["stages"])
    assert _mtimes(work, STAGE_FILES) == before
    assert "skipped" in capsys.readouterr().out
    # --from samples --force redoes samples only
    assert _run(capture, "-w", work, "--from", "samples", "--to", "samples", "--force") == 0
    after = _mtimes(work, STAGE_FILES)
    assert after["samples.npz"] > before["samples.npz"]
    assert after["poses.json"] == before["poses.json"] and after["linear/manifest.json"] == before["linear/manifest.json"]
    # --force on the whole range redoes every stage
    assert _run(capture, "-w", work, "--to", "samples", "--force") == 0
    forced = _mtimes(work, STAGE_FILES)
    assert all(forced[n] > after[n] for n in ("linear/manifest.json", "poses.json", "samples.npz"))


def test_an_unchanged_rerun_keeps_the_report_and_run_record(capture, tmp_path):
    """Nothing ran: report.html and run.json still describe the run that made the outputs (and are
    not redrawn); a stage that runs rewrites both."""
    work = tmp_path / "work"
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses"]) == 0
    before = _mtimes(work, ["report.html", "run.json"])
    assert not any(s["skipped"] for s in json.loads((work / "run.json").read_text())["stages"])
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses"]) == 0
    assert _mtimes(work, ["report.html", "run.json"]) == before
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses", "--force"]) == 0
    after = _mtimes(work, ["report.html", "run.json"])
    assert all(after[n] > before[n] for n in before)


def test_a_changed_input_reruns_the_stages_that_depend_on_it(capture, tmp_path):
    """Freshness is by content (pipeline.workdir): a touched file with the same bytes reruns
    nothing, a changed one reruns the stages that read it and no other."""
    import shutil

    capture = shutil.copytree(capture, tmp_path / "capture")
    work = tmp_path / "work"
    assert _run(capture, "-w", work, "--to", "poses") == 0
    before = _mtimes(work, ["linear/manifest.json", "poses.json"])
    pose_file = capture / "poses.json"
    pose_file.write_text(pose_file.read_text())  # newer, same content: nothing reruns
    assert _run(capture, "-w", work, "--to", "poses") == 0
    assert _mtimes(work, ["linear/manifest.json", "poses.json"]) == before
    pose_file.write_text(json.dumps(json.loads(pose_file.read_text()), indent=3))  # other bytes
    assert _run(capture, "-w", work, "--to", "poses") == 0
    after = _mtimes(work, ["linear/manifest.json", "poses.json"])
    assert after["linear/manifest.json"] == before["linear/manifest.json"]  # linearize does not read it
    assert after["poses.json"] > before["poses.json"]


def test_a_missing_file_the_last_run_wrote_makes_the_stage_stale(tmp_path):
    """An output outside ``outputs()`` (fit/albedo.ply exists only when a texture won) is in the
    record of what the run wrote: removing it makes the stage run again; a file written outside
    the work folder is recorded by its absolute path."""
    from pipeline.workdir import is_fresh, record_settings
    from stages.fit import Settings

    work, settings = tmp_path / "work", Settings()
    named, optional, outside = work / "fit" / "brdf.json", work / "fit" / "albedo.ply", tmp_path / "out.glb"
    for path in (named, optional, outside):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x")
    record_settings(work, "fit", settings, {"sigrend": "test"}, [named, optional, outside])
    assert json.loads((work / "fit.settings.json").read_text())["written"] == sorted(
        ["fit/albedo.ply", "fit/brdf.json", str(outside)]
    )
    assert is_fresh(work, "fit", settings, [named], {"sigrend": "test"})
    outside.unlink()
    assert not is_fresh(work, "fit", settings, [named], {"sigrend": "test"})
    outside.write_text("x")
    optional.unlink()
    assert not is_fresh(work, "fit", settings, [named], {"sigrend": "test"})


def test_run_says_when_it_replaces_a_stage_made_with_other_settings(capture, tmp_path):
    """A stage last run on its own with other settings is run again with run's: the run says so
    (issue 17: a custom `sigrend fit --order 4` was replaced without a word)."""
    import warnings

    work = tmp_path / "work"
    assert cli.main(["linearize", str(capture), "-w", str(work), "--saturation", "0.9"]) == 0
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        assert _run(capture, "-w", work, "--to", "linearize") == 0
    said = [str(w.message) for w in shown if "was last made with" in str(w.message)]
    assert len(said) == 1 and said[0].startswith("linearize was last made with --saturation 0.9"), said
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        assert _run(capture, "-w", work, "--to", "linearize") == 0  # now run's own: nothing to say
    assert not [w for w in shown if "was last made with" in str(w.message)]


def test_failing_stage_is_one_line_and_keeps_earlier_outputs(capture, tmp_path, capsys):
    """A stage failing on a broken poses.json is one line naming the file, the earlier stage's outputs stay as
    they were, and the later stage writes nothing."""
    bad = tmp_path / "bad"
    bad.mkdir()
    for item in capture.iterdir():
        if item.name != "poses.json":
            (bad / item.name).symlink_to(item)
    (bad / "poses.json").write_text("{not json")
    work = tmp_path / "work"
    assert _run(bad, "-w", work, "--to", "linearize") == 0
    before = _mtimes(work, ["linear/manifest.json"])
    capsys.readouterr()
    code = _run(bad, "-w", work, "--to", "samples")
    assert_one_line_error(capsys.readouterr().err, "poses.json", code=code, prefix="sigrend: error:", progress=True)
    assert _mtimes(work, ["linear/manifest.json"]) == before
    assert not (work / "samples.npz").exists()


def test_bad_arguments_are_user_errors(capture, tmp_path, capsys):
    """A missing capture, --from after --to and a missing --relight map are each exit 2 with a message saying
    which."""
    assert _run(tmp_path / "missing", "-w", tmp_path / "w") == 2
    assert "capture folder not found" in capsys.readouterr().err
    assert _run(capture, "-w", tmp_path / "w", "--from", "fit", "--to", "poses") == 2
    assert "comes after" in capsys.readouterr().err
    assert _run(capture, "-w", tmp_path / "w", "--relight", tmp_path / "nope.exr") == 2
    assert "nope.exr" in capsys.readouterr().err


def test_stage_table_lists_every_stage():
    """The stage table has a row per stage between its header and the total, marks the skipped one, and sums the
    times."""
    results = [StageResult(name, [], 1.5, name == "poses") for name in STAGES]
    table = stage_table(results).splitlines()
    assert len(table) == len(STAGES) + 2
    assert "skipped" in table[2] and table[-1].split()[-1] == f"{1.5 * len(STAGES):.1f}"


def test_report_is_self_contained_and_says_what_is_missing(capture, tmp_path, capsys):
    """A run to samples writes report.html with the photos, camera and coverage plots embedded (nothing linked),
    every section's heading, and a line saying the fit has not run."""
    work = tmp_path / "work"
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "samples"]) == 0
    assert f"report: {work / 'report.html'}" in capsys.readouterr().out
    html = (work / "report.html").read_text()
    # the photos (their masks drawn over them), the camera plot and the coverage plot are embedded; nothing is linked
    assert html.count('src="data:image/png;base64,') >= 8 + 2
    assert 'src="http' not in html and 'href="' not in html
    for title in ("Summary", "Photos and masks", "Cameras", "Sample coverage", "Fitted lighting", "Relit vs photo"):
        assert f"<h2>{title}</h2>" in html
    assert "the fit stage has not run" in html


def test_verbose_logs_each_stage_settings_at_its_start(capture, tmp_path):
    """`sigrend -v`: the package logger (pipeline.logs, configured once by the command line) says
    each stage's settings as it starts; without -v it says nothing (linearize of the tiny capture,
    in a process of its own each)."""
    args = [sys.executable, "-m", "pipeline.cli"]
    loud = subprocess.run([*args, "-v", "linearize", str(capture), "-w", str(tmp_path / "w")], capture_output=True, text=True)
    assert loud.returncode == 0, loud.stderr
    line = next(x for x in loud.stderr.splitlines() if x.startswith("sigrend: linearize: running with "))
    assert json.loads(line.split("running with ", 1)[1])["saturation"] == 0.98
    quiet = subprocess.run([*args, "linearize", str(capture), "-w", str(tmp_path / "q")], capture_output=True, text=True)
    assert quiet.returncode == 0 and "running with" not in quiet.stderr


@pytest.mark.slow  # a whole run and a relight of 8 views: ~18 s
def test_relight_takes_a_procedural_lighting(capture, tmp_path, capsys):
    """`sigrend run --relight sun+sky` relights the capture's views under the procedural map (the same
    specs as synth and `sigrend relight --env`), into WORK/relight/sun+sky/, a row of its own in
    run.json; a misspelt spec is one line naming --relight, exit 2, before any stage runs."""
    work = tmp_path / "work"
    assert _run(capture, "-w", work, "--relight", "sun+skyy") == 2
    assert "--relight" in capsys.readouterr().err and not work.exists()
    assert _run(capture, "-w", work, "--relight", "sun+sky") == 0
    run = json.loads((work / "run.json").read_text())
    assert [s["name"] for s in run["stages"]][-1] == "relight-sun+sky"
    renders = sorted((work / "relight" / "sun+sky").glob("*.exr"))
    assert len(renders) == 8
    assert json.loads((work / "relight" / "sun+sky" / "relight.json").read_text())["lighting"]
