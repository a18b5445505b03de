"""`sigrend bench sh --quick`: the CSV and table are written (a smoke test; no timing assertions)."""

import csv
import math

from pipeline.cli import main as sigrend


def test_bench_sh_writes_csv(tmp_path, capsys):
    """sigrend bench sh --quick writes bench_sh.csv with the evaluation and projection cases at their orders,
    every value finite and positive, and prints its rates."""
    assert sigrend(["bench", "sh", "--quick", "--repeat", "1", "-o", str(tmp_path)]) == 0
    with open(tmp_path / "bench_sh.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    cases = {(r["case"], int(r["order"])) for r in rows}
    assert {("sh_evaluate RGB", 8), ("sh_evaluate RGB", 20), ("sh_evaluate RGB", 50), ("project_envmap", 20)} <= cases
    assert all(math.isfinite(float(r["value"])) and float(r["value"]) > 0 for r in rows)
    assert all(r["suite"] == "sh" and r["quick"] == "True" for r in rows)
    assert "directions/s" in capsys.readouterr().out
