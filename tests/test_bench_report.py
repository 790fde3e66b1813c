"""bench/report.py: the generated summary of docs/benchmarks.md."""

from __future__ import annotations

import json

from bench import report


def test_the_summary_sets_each_figure_against_its_goal_and_replaces_only_its_block(tmp_path):
    bench = tmp_path / "bench"
    bench.mkdir()
    (bench / "vision.json").write_text(json.dumps({"recall": 0.97, "precision": 0.98}))
    (bench / "e2e.json").write_text("{not json")
    block, counts = report.summary_block(bench)
    lines = block.splitlines()
    assert lines[0] == report.BEGIN and lines[-1] == report.END
    recall = next(line for line in lines if "recall" in line)
    precision = next(line for line in lines if "| precision" in line)
    assert "97.0 %" in recall and "| ✓ |" in recall and "vision.json" in recall
    assert "98.0 %" in precision and "| ✗ |" in precision
    assert all("not measured" in line for line in lines if "e2e.json" in line)
    assert counts["met"] == 1 and counts["missed"] == 1
    assert counts["not measured"] == len(report.FIGURES) - 2

    page = tmp_path / "benchmarks.md"
    page.write_text("# Benchmarks\n\nIntro.\n\n## Simulator\n\nProse 1.5 ms.\n")
    report.update_page(page, block)
    once = page.read_text()
    assert once.index(report.BEGIN) < once.index("## Simulator") and "Prose 1.5 ms." in once
    (bench / "vision.json").write_text(json.dumps({"recall": 0.90, "precision": 0.995}))
    report.update_page(page, report.summary_block(bench)[0])
    twice = page.read_text()
    assert twice.count(report.BEGIN) == 1 and "90.0 %" in twice and "97.0 %" not in twice
    assert twice.split(report.END, 1)[1] == once.split(report.END, 1)[1]  # the prose is kept
