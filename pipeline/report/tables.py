"""report.html's tables: values as the page shows them (3 significant digits), an HTML table of rows,
a nested dict as rows of key paths, and the fitted material's and fit/report.json's tables
(brdf.json beside the capture's truth gt/brdf.json with each parameter's error, when there is one).

Inputs are the JSON documents the stages write (dicts as read); outputs are HTML strings, every
cell escaped.
"""

from __future__ import annotations

import html

import numpy as np


def format_value(value) -> str:
    """A value as the page shows it: numbers to 3 significant digits, lists joined, None as '—'."""
    if isinstance(value, bool) or value is None:
        return "—" if value is None else ("yes" if value else "no")
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.3g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_value(v) for v in value)
    if isinstance(value, dict):
        return "; ".join(f"{k}: {format_value(v)}" for k, v in value.items())
    return str(value)


def html_table(rows: list, header: list[str] | None = None) -> str:
    """An HTML table of ``rows`` (each a list of cells, formatted by format_value and escaped)."""
    head = "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>" if header else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(format_value(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


def flat_rows(doc: dict, prefix: str = "") -> list[list]:
    """Rows [key path, value] of a nested dict (lists of scalars stay one value)."""
    rows = []
    for k, v in doc.items():
        if isinstance(v, dict):
            rows += flat_rows(v, f"{prefix}{k}.")
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            rows.append([f"{prefix}{k}", f"{len(v)} entries"])
        else:
            rows.append([f"{prefix}{k}", v])
    return rows


def brdf_table(brdf: dict, truth: dict | None) -> str:
    """The fitted material's parameters (3 significant digits); with the capture's truth (gt/brdf.json,
    synthetic captures) a truth column and each parameter's error (fit − truth, and relative)."""
    materials = brdf.get("materials")
    shown = {k: v for k, v in brdf.items() if k != "materials"}
    if truth is None or truth.get("model") != brdf.get("model"):
        note = (
            ""
            if truth is None
            else (
                f"<p>The capture's truth (gt/brdf.json) is a {html.escape(str(truth.get('model')))} "
                "material: not compared parameter by parameter.</p>"
            )
        )
        out = note + html_table([[k, v] for k, v in shown.items()], ["parameter", "fitted"])
    else:
        rows = []
        for k, v in shown.items():
            t = truth.get(k)
            err = rel = None
            if t is not None and isinstance(v, (int, float, list)) and not isinstance(v, bool):
                fv, tv = np.atleast_1d(np.asarray(v, float)), np.atleast_1d(np.asarray(t, float))
                if fv.shape == tv.shape:
                    err = (fv - tv).tolist()
                    rel = [f"{100 * (a - b) / abs(b):+.3g}%" if b != 0 else "—" for a, b in zip(fv, tv)]
                    err, rel = (err[0], rel[0]) if fv.size == 1 else (err, ", ".join(rel))
            rows.append([k, v, t, err, rel])
        out = "<p>Against the capture's truth (gt/brdf.json).</p>" + html_table(
            rows, ["parameter", "fitted", "truth", "error (fit − truth)", "relative error"]
        )
    if materials:
        keys = sorted({k for m in materials for k in m if k != "model"})
        out += "<h3>Materials (fit/material.ply's material_id)</h3>" + html_table(
            [[i, m.get("model")] + [m.get(k) for k in keys] for i, m in enumerate(materials)], ["id", "model", *keys]
        )
    return out


def fit_tables(report: dict) -> str:
    """fit/report.json as tables: the choices, the candidates compared, and the rest of its entries."""
    parts = []
    chosen = [[k, report[k]] for k in ("mode", "forward_model", "order", "brdf_model") if k in report]
    selection = report.get("model_selection")
    if isinstance(selection, dict):
        chosen += [[f"model selection: {k}", v] for k, v in selection.items() if not isinstance(v, (dict, list))]
    parts.append("<h3>What the fit chose</h3>" + html_table(chosen, ["", "value"]))
    cands = report.get("candidates") or []
    if cands and isinstance(cands, list) and isinstance(cands[0], dict):
        cols = [c for c in ("name", "params", "train_rmse", "validation_rmse", "seconds") if any(c in r for r in cands)]
        parts.append(
            "<h3>Candidates compared (lowest validation RMSE wins, within the parsimony rule)</h3>"
            + html_table([[r.get(c) for c in cols] for r in cands], [c.replace("_", " ") for c in cols])
        )
    shown = {
        "mode",
        "forward_model",
        "order",
        "brdf_model",
        "model_selection",
        "candidates",
        "bands",
        "labels",
        "residuals_per_view",
        "brdf",
        "schema",
    }
    rest = {k: v for k, v in report.items() if k not in shown}
    if rest:
        parts.append(
            "<details><summary>Everything else in fit/report.json</summary>"
            + html_table(flat_rows(rest), ["entry", "value"])
            + "</details>"
        )
    return "".join(parts)
