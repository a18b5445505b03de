"""pipeline.report: report.html from whatever a work folder holds — every section says what is
missing instead of failing, a finished run's page holds its numbers and pictures inline, and
the texture picture draws each side where it is."""

from pathlib import Path

import numpy as np
import trimesh

from pipeline.io.images import read_image
from pipeline.report import build_report, texture_views

SAMPLE = Path(__file__).parents[1] / "sample_data" / "capture"


def test_an_empty_work_folder_says_what_has_not_run(tmp_path):
    page = build_report(SAMPLE, tmp_path / "work")
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    for missing in ("no fitted lighting yet", "no fitted BRDF yet", "no relight comparison yet"):
        assert missing in page
    assert "http://" not in page and "https://" not in page     # self-contained: no external references


def test_a_finished_run_shows_its_numbers_inline(tmp_path):
    """A work folder with a fit (a principled brdf.json and a uniform lighting_sh.json): the BRDF table and
    the lighting pictures are in the page as data URIs."""
    work = tmp_path / "work"
    (work / "fit").mkdir(parents=True)
    (work / "fit" / "brdf.json").write_text('{"model": "principled", "base_color": [0.45, 0.3, 0.2], '
                                            '"roughness": 0.35, "metallic": 0.0, "ior": 1.5}')
    coeffs = np.zeros((9, 3))
    coeffs[0] = 1.0
    from pipeline.io.lighting import write_lighting_sh

    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs)
    page = build_report(SAMPLE, work)
    assert "0.35" in page and "data:image/png;base64," in page
    assert "no fitted BRDF yet" not in page


def test_texture_views_put_each_side_where_it_is(tmp_path):
    """A sphere red where x > 0, black elsewhere: seen from +X the middle is red, from -X black."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    colour = np.where(mesh.vertices[:, :1] > 0, [[0.8, 0.05, 0.05]], [[0.0, 0.0, 0.0]])
    (tmp_path / "t.png").write_bytes(texture_views(np.asarray(mesh.vertices), np.asarray(mesh.faces), colour))
    img = read_image(tmp_path / "t.png")[..., :3]
    panels = np.array_split(img, 5, axis=1)         # from +X, +Y, -X, -Y, above
    centre = [p[p.shape[0] // 2 - 3:p.shape[0] // 2 + 3, p.shape[1] // 2 - 3:p.shape[1] // 2 + 3].mean(axis=(0, 1))
              for p in panels]
    assert centre[0][0] > 0.6 and centre[0][1] < 0.4      # +X: red (sRGB)
    assert centre[2].max() < 0.15                          # -X: black
