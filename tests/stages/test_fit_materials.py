"""fit --materials auto on a capture of one material: the step runs end to end (candidates shaded under
the fitted lighting, the map refitted per fold) and the held-out views keep one material."""

from __future__ import annotations

import json

import pytest

from pipeline import cli

# synth's EXR photos carry no EXIF: linearize says it assumes one exposure for all
pytestmark = pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image:UserWarning")


@pytest.mark.slow
def test_one_material_object_keeps_one_material(tiny_capture, tmp_path):
    """A uniform Lambertian sphere (synth, 6 views): report.json's `materials` compares one material
    with the candidates' map by held-out RMSE and keeps one, so brdf.json lists no materials and no
    material.ply is written (a map would be a model of more than the scene needs)."""
    capture = tiny_capture(mesh="sphere", brdf="lambert:albedo=0.6", env="area", views=6, size=(64, 64))
    work = tmp_path / "work"
    assert cli.main(["run", str(capture), "-w", str(work), "--to", "samples", "--no-report"]) == 0
    assert (
        cli.main(
            [
                "fit",
                str(capture),
                "-w",
                str(work),
                "--materials",
                "auto",
                "--physical-samples",
                "3000",
                "--roughness-candidates",
                "0.3,1.0",
            ]
        )
        == 0
    )
    report = json.loads((work / "fit" / "report.json").read_text())
    entry = report["materials"]
    assert [c["name"].split(",")[0] for c in entry["candidates"]][0] == "one material"
    assert entry["choice"].startswith("one material") and len(entry["tried"]) >= 5
    assert "materials" not in json.loads((work / "fit" / "brdf.json").read_text())
    assert not (work / "fit" / "material.ply").exists()
