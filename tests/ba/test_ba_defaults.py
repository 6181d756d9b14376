"""The bundle-adjustment defaults are the ones the measurement chose: docs/ba_defaults.json
(written by benchmarks/bench_ba_defaults.py, explained in docs/ba.md). No model runs:
the criterion is recomputed here from the JSON's own per-scene numbers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from rvggt_jax.ba.refine import BAOptions

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "ba_defaults.json"


@pytest.fixture(scope="module")
def doc():
    return json.loads(RESULTS.read_text())


def _key(row):
    return row["query_frames"], row["query_points"]


def test_rows_agree_with_their_scenes(doc):
    """Each row's aggregates are those of its per-scene runs (means of the scores, median
    of the seconds, usable only where usable on every scene), for every scene."""
    seeds = doc["seeds"]
    assert len(seeds) >= 2 and all(0 <= s < 100_000 for s in seeds)  # held-out scenes
    for row in doc["rows"]:
        runs = row["per_scene"]
        assert [r["seed"] for r in runs] == seeds, _key(row)
        assert row["usable"] == all(r["usable"] for r in runs), _key(row)
        assert row["seconds"] == pytest.approx(np.median([r["seconds"] for r in runs]))
        if row["usable"]:
            for agg, key in (("auc30_after", "auc30_after"), ("rot_err_after", "rot_err_after"),
                             ("reproj_after", "reproj_after")):
                assert row[agg] == pytest.approx(np.mean([r[key] for r in runs])), (_key(row), agg)
        before = doc["model_before"]
        assert row["auc30_before"] == pytest.approx(np.mean([b["auc@30"] for b in before]))


def test_grid_covers_upstream_and_the_old_default(doc):
    keys = {_key(r) for r in doc["rows"]}
    frames = doc["frames"]
    assert (min(8, frames), 4096) in keys  # upstream VGGT's (VGGSfM's) 8 query frames, 4096 points
    assert (4, 512) in keys  # this package's defaults before the measurement
    assert len(keys) == len(doc["rows"])


def test_chosen_row_is_optimal_by_the_stated_criterion(doc):
    """Recomputed: among the rows usable on every scene within the time budget, those
    within `auc_tolerance` of the best mean AUC@30 after BA, the fastest (ties: fewer
    frames, then fewer points)."""
    crit = doc["criterion"]
    assert crit["metric"] == "auc30_after" and crit["cost"] == "seconds"
    usable = [r for r in doc["rows"] if r["usable"] and r["seconds"] <= crit["budget_s"]]
    assert usable, "no setting was usable on every scene"
    best = max(r["auc30_after"] for r in usable)
    near = [r for r in usable if r["auc30_after"] >= best - crit["auc_tolerance"]]
    want = min(near, key=lambda r: (r["seconds"], r["query_frames"], r["query_points"]))
    marked = [r for r in doc["rows"] if r["chosen"]]
    assert len(marked) == 1 and _key(marked[0]) == _key(want)
    assert (doc["chosen"]["query_frames"], doc["chosen"]["query_points"]) == _key(want)


def test_defaults_are_the_chosen_row(doc):
    d = BAOptions()
    assert (d.query_frames, d.query_points) == (doc["chosen"]["query_frames"], doc["chosen"]["query_points"])


def test_cli_help_states_the_defaults(capsys):
    from rvggt_jax.app.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["reconstruct", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    d = BAOptions()
    frames = re.search(r"--ba-query-frames N (.*?)--ba-query-points", text).group(1)
    points = re.search(r"--ba-query-points N (.*?)--ba-", text).group(1)
    assert f"(default {d.query_frames})" in frames, frames
    assert f"(default {d.query_points})" in points, points
