"""pipeline.report: report.html from whatever a work folder holds — every section says what is
missing instead of failing, a finished run's page holds its numbers and pictures inline, the
texture picture draws each side where it is, the truth beside the fit, the run's warnings, and
the page as a browser shows it (headless Chromium: no blank picture, no text out of its box)."""

import contextlib
import html
import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline import cli
from pipeline.core.brdf import Brdf
from pipeline.core.material import material_from_brdf
from pipeline.core.sh import sh_evaluate
from pipeline.core.shading import specular_samples
from pipeline.core.transfer import irradiance_from_sh
from pipeline.io.images import read_image
from pipeline.report import build_report
from pipeline.report.figures import principled_sphere, texture_views

SAMPLE = Path(__file__).parents[1] / "sample_data" / "capture"


def test_an_empty_work_folder_says_what_has_not_run(tmp_path):
    """An empty work folder still gives a whole page saying that the lighting, the BRDF and the relight
    comparison are not there yet, with no external reference."""
    page = build_report(SAMPLE, tmp_path / "work")
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    for missing in ("no fitted lighting yet", "no fitted BRDF yet", "no relight comparison yet"):
        assert missing in page
    assert "http://" not in page and "https://" not in page  # self-contained: no external references


def test_a_finished_run_shows_its_numbers_inline(tmp_path):
    """A work folder with a fit (a principled brdf.json and a uniform lighting_sh.json): the BRDF table and
    the lighting pictures are in the page as data URIs."""
    work = tmp_path / "work"
    (work / "fit").mkdir(parents=True)
    (work / "fit" / "brdf.json").write_text(
        '{"model": "principled", "base_color": [0.45, 0.3, 0.2], "roughness": 0.35, "metallic": 0.0, "ior": 1.5}'
    )
    coeffs = np.zeros((9, 3))
    coeffs[0] = 1.0
    from pipeline.io.lighting import write_lighting_sh

    write_lighting_sh(work / "fit" / "lighting_sh.json", coeffs)
    page = build_report(SAMPLE, work)
    assert "0.35" in page and "data:image/png;base64," in page
    assert "no fitted BRDF yet" not in page


def test_a_skipped_texel_step_says_why(tmp_path):
    """A fit whose per-texel step did not run (report.json "texels": ran false, with texels_called_for's
    why) says so in words in the BRDF section, instead of leaving the map out without a word."""
    work = tmp_path / "work"
    (work / "fit").mkdir(parents=True)
    (work / "fit" / "brdf.json").write_text('{"model": "lambert", "albedo": [0.5, 0.4, 0.3]}')
    why = "the subset chose a uniform albedo & was dense enough to decide"
    (work / "fit" / "report.json").write_text(json.dumps({"texels": {"setting": "auto", "ran": False, "why": why}}))
    page = build_report(SAMPLE, work)
    assert f"<b>Base colour per texel:</b> not fitted ({html.escape(why)})" in page


def test_texture_views_put_each_side_where_it_is(tmp_path):
    """A sphere red where x > 0, black elsewhere: seen from +X the middle is red, from -X black."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    colour = np.where(mesh.vertices[:, :1] > 0, [[0.8, 0.05, 0.05]], [[0.0, 0.0, 0.0]])
    (tmp_path / "t.png").write_bytes(texture_views(np.asarray(mesh.vertices), np.asarray(mesh.faces), colour))
    img = read_image(tmp_path / "t.png")[..., :3]
    panels = np.array_split(img, 5, axis=1)  # from +X, +Y, -X, -Y, above
    centre = [
        p[p.shape[0] // 2 - 3 : p.shape[0] // 2 + 3, p.shape[1] // 2 - 3 : p.shape[1] // 2 + 3].mean(axis=(0, 1)) for p in panels
    ]
    assert centre[0][0] > 0.6 and centre[0][1] < 0.4  # +X: red (sRGB)
    assert centre[2].max() < 0.15  # -X: black


def test_the_truth_stands_beside_the_fit_with_each_parameter_error(tmp_path):
    """A capture with gt/brdf.json: the BRDF table has a truth column and each parameter's error
    (fit − truth and relative), numbers to 3 significant digits (roughness 0.32412345 for 0.35:
    error -0.0259, -7.39 %)."""
    capture, work = tmp_path / "cap", tmp_path / "work"
    (capture / "gt").mkdir(parents=True)
    (work / "fit").mkdir(parents=True)
    (capture / "gt" / "brdf.json").write_text(
        '{"model": "principled", "base_color": [0.45, 0.3, 0.2], "roughness": 0.35, "metallic": 0.0, "ior": 1.5}'
    )
    (work / "fit" / "brdf.json").write_text(
        '{"model": "principled", "base_color": [0.44212345, 0.289, 0.194], "roughness": 0.32412345, "metallic": 0.0, "ior": 1.5}'
    )
    page = build_report(capture, work)
    cells = [re.findall(r"<td>(.*?)</td>", row) for row in re.findall(r"<tr>(.*?)</tr>", page)]
    rows = {c[0]: c[1:] for c in cells if c}
    assert rows["roughness"] == ["0.324", "0.35", "-0.0259", "-7.39%"]
    assert rows["base_color"][:2] == ["0.442, 0.289, 0.194", "0.45, 0.3, 0.2"]
    assert rows["base_color"][3] == "-1.75%, -3.67%, -3%"
    assert "0.32412345" not in page and "0.44212345" not in page


# linear EXR renders carry no EXIF: linearize warns (kept as warnings here: the run records them)
EXPOSURE_WARNINGS = "default:no (exposure time|ISO|f-number) in any image:UserWarning"


@pytest.mark.filterwarnings(EXPOSURE_WARNINGS)
def test_the_runs_warnings_are_recorded_and_get_a_section(tiny_capture, tmp_path):
    """The warnings a run raises (here linearize's 'no exposure time ...' on EXIF-less EXRs) are
    kept in run.json and listed in the report's Warnings section, and still reach the caller."""
    capture, work = tiny_capture(views=8, size=(48, 48)), tmp_path / "work"
    with pytest.warns(UserWarning, match="no exposure time"):
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli.main(["run", str(capture), "-w", str(work), "--to", "linearize"]) == 0
    found = json.loads((work / "run.json").read_text())["warnings"]
    assert any(w.startswith("no exposure time in any image") for w in found), found
    page = (work / "report.html").read_text()
    section = page[page.index(f"<h2>Warnings ({len(found)})</h2>") :]
    section = section[: section.index("</section>")]
    assert all(html.escape(w) in section for w in found)


MEASURE_JS = """
window.addEventListener("load", () => {
  const out = {images: [], overflow: [], width: document.documentElement.clientWidth};
  const canvas = document.createElement("canvas");
  const ctx = canvas.getContext("2d", {willReadFrequently: true});
  for (const img of document.images) {
    const r = img.getBoundingClientRect();
    let spread = -1;
    if (img.complete && img.naturalWidth > 0) {
      canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
      ctx.drawImage(img, 0, 0);
      const d = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
      let lo = 255, hi = 0;
      for (let i = 0; i < d.length; i += 4) {
        const v = (d[i] + d[i + 1] + d[i + 2]) / 3;
        if (v < lo) lo = v; if (v > hi) hi = v;
      }
      spread = hi - lo;
    }
    out.images.push({alt: img.alt, natural: img.naturalWidth, shown: r.width, right: r.right, spread: spread});
  }
  for (const el of document.querySelectorAll("h1,h2,h3,p,li,td,th,figcaption,summary,table,figure")) {
    if (el.closest("details:not([open])")) continue;
    const r = el.getBoundingClientRect();
    if (el.scrollWidth > el.clientWidth + 1 || r.right > out.width + 1)
      out.overflow.push({tag: el.tagName, text: el.textContent.slice(0, 80), right: r.right});
  }
  const pre = document.createElement("pre");
  pre.id = "sigrend-measurements";
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
"""
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--hide-scrollbars",
    "--window-size=1024,768",
    "--virtual-time-budget=10000",
]


@pytest.mark.slow
@pytest.mark.filterwarnings(EXPOSURE_WARNINGS)
@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (Debian: apt-get install chromium)")
def test_the_report_in_a_browser_has_no_blank_picture_and_no_text_out_of_its_box(tiny_capture, tmp_path):
    """`sigrend run` on a small synthetic capture (8 views of 48 x 48, gt/ included), its report.html
    opened in headless Chromium at 1024 px: every picture loads and is not one flat colour (its
    grey levels span at least 3 of 255: the old all-white mask squares span 0; a good fit's error maps,
    black to dark purple, measured 4 and 7), none reaches past the window (the old coverage plot did), no
    cell, caption or heading overflows its box (measured by a script run in a copy of the page, the
    numbers written into the DOM and read back with --dump-dom); a full-page screenshot is not blank."""
    capture, work = tiny_capture(views=8, size=(48, 48)), tmp_path / "work"
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(["run", str(capture), "-w", str(work)]) == 0
    page = (work / "report.html").read_text()
    assert "<script" not in page and "http://" not in page and "https://" not in page  # self-contained, inert
    for title in ("Warnings", "Photos and masks", "Sample coverage", "Fitted lighting", "BRDF", "Relit vs photo"):
        assert f"<h2>{title}" in page, title
    assert "<th>truth</th>" in page
    probe = tmp_path / "probe.html"
    probe.write_text(page.replace("</body>", f"<script>{MEASURE_JS}</script></body>"))
    dom = subprocess.run([CHROMIUM, *BROWSER, "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=300).stdout
    found = re.search(r'<pre id="sigrend-measurements">(.*?)</pre>', dom, re.S)
    assert found, dom[-2000:]
    measured = json.loads(html.unescape(found.group(1)))
    assert len(measured["images"]) == page.count("<img ")
    blank = [(i["alt"], i["spread"]) for i in measured["images"] if i["natural"] == 0 or i["spread"] < 3]
    assert not blank, blank
    wide = [(i["alt"], i["right"]) for i in measured["images"] if i["right"] > measured["width"] + 1]
    assert not wide, (measured["width"], wide)
    assert not measured["overflow"], measured["overflow"]
    shot = tmp_path / "report.png"
    subprocess.run(
        [CHROMIUM, *BROWSER[:-2], "--window-size=1024,4000", f"--screenshot={shot}", (work / "report.html").as_uri()],
        capture_output=True,
        timeout=300,
    )
    pixels = read_image(shot)[..., :3]
    assert pixels.shape[1] == 1024 and pixels.std() > 0.05, pixels.std()


def test_the_sphere_preview_is_the_material_of_the_core_shading_path():
    """The report's 'fitted material' sphere is the core material's reflection equation: at a few pixels
    it equals, to round-off, the diffuse layer / pi x the SH irradiance plus, over the lobe's importance
    samples, f cos / pdf (Principled.eval_cos without its diffuse part, times the sample's 1 / (S pdf))
    times the lighting along the sample — a metal-dielectric mix, so F0, Fresnel and the energy
    compensation are all in the comparison."""
    brdf = Brdf("principled", base_color=(0.6, 0.35, 0.2), roughness=0.4, metallic=0.3, ior=1.5)
    rng = np.random.default_rng(3)
    coeffs = 0.2 * rng.standard_normal((25, 3))
    coeffs[0] = 2.0  # a positive lighting, order 4
    xz = np.array([[0.0, 0.0], [0.3, 0.2], [-0.5, 0.4], [0.6, -0.55], [-0.1, -0.8]])
    normal = np.column_stack([xz[:, 0], np.sqrt(1 - (xz**2).sum(axis=1)), xz[:, 1]])
    view = np.tile([0.0, 1.0, 0.0], (len(normal), 1))
    preview = principled_sphere(coeffs, brdf, normal, view)

    material = material_from_brdf(brdf)
    mu_out = normal[:, 1]
    kd = material.diffuse_weight(mu_out)  # base colour x the diffuse layer
    lobe = specular_samples(material, normal, view, 64, np.random.default_rng(0))
    s = lobe.directions.shape[1]
    w_in = lobe.directions.reshape(-1, 3)
    n, v = (np.repeat(a, s, axis=0) for a in (normal, view))
    mu_in = np.einsum("pc,pc->p", n, w_in)
    spec = material.eval_cos(n, w_in, v) - np.repeat(kd, s, axis=0) * (np.maximum(mu_in, 0) / np.pi)[:, None]
    seen = np.maximum(sh_evaluate(coeffs, w_in), 0.0)
    lobe_sum = (spec * lobe.solid_angle.reshape(-1, 1) * seen).reshape(len(normal), s, 3).sum(axis=1)
    expected = kd / np.pi * irradiance_from_sh(coeffs, normal) + lobe_sum
    assert (lobe_sum > 0.1 * expected).all()  # the lobe is a real part of each pixel
    np.testing.assert_allclose(preview, expected, rtol=1e-10, atol=0)
