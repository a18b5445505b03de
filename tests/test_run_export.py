"""`sigrend run --export ASSET` (issue 48 item 3): the run ends with the exported asset, a row of its
own in the stage table; a bad asset name or a run that stops before the fit is one line, exit 2,
before any stage runs."""

from __future__ import annotations

import json

import pygltflib
import pytest
import trimesh
from helpers import assert_one_line_error

from pipeline import cli

# linear EXR renders carry no EXIF: linearize warns once per run and assumes equal exposure
pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning")


@pytest.mark.slow
def test_run_ends_with_the_asset(tiny_capture, tmp_path, capsys):
    """A tiny synth capture (8 views, 48 x 48) run end to end with --export: run.json's last stage is
    export and lists the asset, the printed stage table has its row, and the .glb read back with
    pygltflib holds one mesh with the capture's vertex count, its lighting map and manifest beside it."""
    capture = tiny_capture(views=8, size=(48, 48))
    work, asset = tmp_path / "work", tmp_path / "out" / "asset.glb"
    assert cli.main(["run", str(capture), "-w", str(work), "--no-report", "--export", str(asset)]) == 0
    stages = json.loads((work / "run.json").read_text())["stages"]
    assert [s["name"] for s in stages][-2:] == ["relight-check", "export"]
    assert str(asset) in stages[-1]["outputs"]
    table = capsys.readouterr().out
    assert any(line.split()[:2] == ["export", "ran"] for line in table.splitlines())
    doc = pygltflib.GLTF2().load(str(asset))
    vertices = len(trimesh.load(capture / "mesh.ply", process=False).vertices)
    assert len(doc.meshes) == 1 and doc.accessors[doc.meshes[0].primitives[0].attributes.POSITION].count == vertices
    assert (asset.parent / "asset.glb.lighting.exr").is_file()
    assert json.loads((asset.parent / "asset.glb.export.json").read_text())["asset"] == "asset.glb"


def test_a_bad_export_is_one_line_before_any_stage(tiny_capture, tmp_path, capsys):
    """--export to a format export cannot write, or with --to before the fit: exit 2, one line, and
    no stage has run (no work folder)."""
    capture = tiny_capture(views=8, size=(48, 48))
    work = tmp_path / "work"
    assert cli.main(["run", str(capture), "-w", str(work), "--export", str(tmp_path / "asset.usdz")]) == 2
    assert_one_line_error(capsys.readouterr().err, "glTF, USD or Mitsuba")
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "poses", "--export", str(tmp_path / "a.glb")]) == 2
    assert_one_line_error(capsys.readouterr().err, "--export needs the fit")
    assert not work.exists()
