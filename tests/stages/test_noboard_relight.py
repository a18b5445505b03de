"""The no-board JPEG capture end to end (issue 49 item 2): `sigrend run` on 32 JPEGs of a textured glossy
Suzanne with no board and no poses (tests/data/blender_noboard: COLMAP registered to the mesh, then the
fit with lighting and material unknown), then relit under another HDRI from four novel views and
compared with Cycles' renders of them (score_relight.py's metric: 4 x 4 block means, one scale per
channel)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import DATA, blender_world

from pipeline import cli
from pipeline.core.image_metrics import block_relative_rmse
from pipeline.io.images import read_image, write_image

CAPTURE = DATA / "blender_noboard"

# the product's own warnings on this capture, not faults of the test: the JPEGs carry no EXIF (linearize
# takes one exposure for all: true, one camera setting); Suzanne's mesh has open eye sockets (holes)
pytestmark = [
    pytest.mark.filterwarnings("ignore:no (exposure time|ISO|f-number) in any image's EXIF:UserWarning"),
    pytest.mark.filterwarnings("ignore:.*boundary edges \\(holes, an open scan\\):UserWarning"),
]


@pytest.mark.slow
def test_noboard_capture_relights_under_a_new_hdri(tmp_path: Path):
    """With every default (about 2 min 40 s here, the fit 140 s), the fit finds the glossy dielectric
    (principled, roughness within 20 % of the true 0.5: measured 0.502) with a per-texel base colour, and
    the four novel views relit under city.exr are within 18 % of Cycles (measured 13.7 %; the issue's
    target is 6 %: the texture's edges and the base colour's detail are what is left).  Before
    2026-12-07 the default fit chose Lambert (the material was chosen with a uniform base colour, whose
    texture variance hid the specular layer) and relit at 28.9 % (21.1 % re-chosen, without texels)."""
    import json

    work, out = tmp_path / "work", tmp_path / "relit"
    assert cli.main(["run", str(CAPTURE), "-w", str(work), "--to", "fit", "--no-report"]) == 0
    brdf = json.loads((work / "fit" / "brdf.json").read_text())
    assert brdf["model"] == "principled" and brdf["metallic"] == 0.0, brdf
    assert brdf["roughness"] == pytest.approx(0.5, rel=0.2), brdf
    write_image(tmp_path / "city.exr", blender_world(DATA / "hdri" / "city.exr", 0), dtype="float")
    views = CAPTURE / "gt" / "relight" / "poses.json"
    args = ["relight", str(CAPTURE), "-w", str(work), "--env", str(tmp_path / "city.exr"), "--views", str(views), "-o", str(out)]
    assert cli.main(args) == 0
    names = sorted(json.loads(views.read_text())["images"])
    refs = [read_image(CAPTURE / "gt" / "relight" / "images" / n) for n in names]
    err = block_relative_rmse([read_image(out / n) for n in names], refs)
    assert err.total < 0.18, err
