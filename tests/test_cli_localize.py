"""`topomap localize` and `topomap eval` through typer's CliRunner: JSON per query, image / folder /
video queries, the three ground-truth formats, --plot, every bad input of issue 3 (one "Error:" line,
exit 1, no traceback) and the corridor check of the issue."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import assert_error as cli_error
from conftest import corridor_map_file, dataset, tamper
from fuzz_cases import reseal
from map_synth import FRAME_SIZE, scene, window, write_sequence, write_video
from typer.testing import CliRunner

STEP = 120.0
XS = np.arange(0.0, 16 * STEP, STEP)  # 16 map views, img0.png .. img15.png
QUERIES = (2, 5, 8, 11)  # second-pass views used as queries


def assert_error(result, *fragments: str) -> str:
    """One "Error: ..." line, exit 1, no traceback (progress and warning lines before it allowed)."""
    return cli_error(result, *fragments, alone=False)


def ok_json(result):
    assert result.exit_code == 0, result.output
    assert result.exception is None and "Traceback" not in result.output
    return json.loads(result.stdout)


def second_pass(tex: np.ndarray, i: int) -> np.ndarray:
    rng = np.random.default_rng(100 + i)
    return np.clip(window(tex, XS[i] + 5.0, y=43.0) + rng.normal(0, 4.0, FRAME_SIZE[::-1]), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    """A synthetic map built through the CLI, query images (folder, single image, video), and the
    ground truth in the three formats."""
    from topomap_cli.main import app

    root = tmp_path_factory.mktemp("clilocalize")
    tex = scene(3, width=3000)
    write_sequence(root / "map", [window(tex, x, y=40.0) for x in XS])
    result = CliRunner().invoke(app, ["build", str(root / "map"), "-o", str(root / "m.topomap"), "--max-features", "500"])
    assert result.exit_code == 0, result.output
    q = root / "queries"
    q.mkdir()
    for i in QUERIES:
        cv2.imwrite(str(q / f"q{i}.png"), second_pass(tex, i))
    write_video(root / "walk.avi", [second_pass(tex, i) for i in QUERIES])
    same = root / "same"  # the second pass named like the map's images (Nordland style)
    same.mkdir()
    for i in QUERIES:
        cv2.imwrite(str(same / f"img{i}.png"), second_pass(tex, i))
    (root / "gt.csv").write_text("query_file,query_idx,matching_ref_indices\n" + "".join(
        f"queries/q{i}.png,{i},{i - 1};{i};{i + 1}\n" for i in QUERIES))
    (root / "map_poses.csv").write_text("image,x,z,theta\n" + "".join(f"img{i}.png,{x / 100},0,0\n" for i, x in enumerate(XS)))
    (root / "query_poses.csv").write_text("image,x,z,theta\n" + "".join(f"q{i}.png,{(XS[i] + 5) / 100},0.03,0\n" for i in QUERIES))
    return {"root": root, "map": root / "m.topomap", "queries": q, "video": root / "walk.avi", "same": same,
            "gt": root / "gt.csv", "map_poses": root / "map_poses.csv", "query_poses": root / "query_poses.csv"}


def right_frames(i: int) -> set[str]:
    return {f"img{j}.png" for j in (i - 1, i, i + 1)}


# ============================================================================= localize
def test_localize_folder_json(runner, cli_app, data):
    rows = ok_json(runner.invoke(cli_app, ["localize", str(data["map"]), str(data["queries"]), "--json"]))
    assert [r["query"] for r in rows] == [f"q{i}.png" for i in QUERIES]  # natural order, file names
    for i, r in zip(QUERIES, rows):
        assert {"query", "node", "frames", "confidence", "status"} <= set(r)
        assert isinstance(r["node"], int) and 0.0 <= r["confidence"] <= 1.0
        assert r["status"] == "localized" and set(r["frames"]) & right_frames(i), r
        assert all(f.startswith("img") for f in r["frames"])


def test_localize_single_image_and_table(runner, cli_app, data):
    image = data["queries"] / "q8.png"
    rows = ok_json(runner.invoke(cli_app, ["localize", str(data["map"]), str(image), "--json"]))
    assert len(rows) == 1 and rows[0]["query"] == "q8.png" and set(rows[0]["frames"]) & right_frames(8)
    table = runner.invoke(cli_app, ["localize", str(data["map"]), str(image)])
    assert table.exit_code == 0 and "q8.png" in table.stdout and "localized" in table.stdout


def test_localize_video_and_sequence(runner, cli_app, data):
    rows = ok_json(runner.invoke(cli_app, ["localize", str(data["map"]), str(data["video"]), "--json"]))
    assert [r["query"] for r in rows] == [f"frame_{k:06d}" for k in range(len(QUERIES))]
    assert all(set(r["frames"]) & right_frames(i) for i, r in zip(QUERIES, rows))
    seq = ok_json(runner.invoke(cli_app, ["localize", str(data["map"]), str(data["queries"]), "--sequence", "--json"]))
    assert len(seq) == len(QUERIES) and all({"query", "node", "frames", "confidence", "status"} <= set(r) for r in seq)
    assert set(seq[-1]["frames"]) & right_frames(QUERIES[-1])


def test_localize_thumbnail_descriptor_and_threshold(runner, cli_app, data):
    rows = ok_json(runner.invoke(cli_app, ["localize", str(data["map"]), str(data["queries"]), "--json",
                                           "--descriptor", "thumbnail", "--min-confidence", "1.0"]))
    assert all(r["status"] == "unknown" for r in rows if r["confidence"] < 1.0)
    assert all(r["status"] == "localized" for r in rows if r["confidence"] >= 1.0)


# ============================================================================= eval
EVAL_KEYS = {"queries", "queries_with_match", "recall_at_1", "recall_at_5", "recall_at_10", "auc",
             "recall_at_100_precision", "mode", "descriptor", "ms_per_query", "skipped", "declared", "declared_right",
             "declared_precision", "ece", "calibrated"}


def test_eval_with_a_correspondence_csv_and_plot(runner, cli_app, data, tmp_path):
    plot = tmp_path / "pr.png"
    d = ok_json(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), "--ground-truth",
                                        str(data["gt"]), "--plot", str(plot), "--json"]))
    assert EVAL_KEYS <= set(d) and d["queries"] == d["queries_with_match"] == len(QUERIES)
    assert d["recall_at_1"] == 1.0 and d["mode"] == "single" and d["descriptor"] == "fused"
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), "--ground-truth", str(data["gt"]),
                                    "--sequence"])
    assert table.exit_code == 0 and "recall at 1" in table.stdout and "sequence" in table.stdout


def test_eval_same_name(runner, cli_app, data):
    d = ok_json(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["same"]), "--ground-truth", "same-name",
                                        "--tolerance", "1", "--json"]))
    assert d["queries_with_match"] == len(QUERIES) and d["recall_at_1"] == 1.0


def test_eval_with_poses(runner, cli_app, data):
    args = ["eval", str(data["map"]), str(data["queries"]), "--ground-truth", str(data["query_poses"]),
            "--map-poses", str(data["map_poses"]), "--json"]
    d = ok_json(runner.invoke(cli_app, [*args, "--radius", "1.3"]))  # views 1.2 m apart: i-1, i, i+1
    assert d["queries_with_match"] == len(QUERIES) and d["recall_at_1"] == 1.0
    none = ok_json(runner.invoke(cli_app, [*args, "--radius", "0.01"]))  # no map frame that close
    assert none["queries_with_match"] == 0 and none["recall_at_1"] == 0.0


# ============================================================================= bad input
def test_unreadable_query_image(runner, cli_app, data, tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    assert_error(runner.invoke(cli_app, ["localize", str(data["map"]), str(bad)]), "broken.png is not a valid PNG")
    assert_error(runner.invoke(cli_app, ["localize", str(data["map"]), str(tmp_path / "nothing.png")]), "does not exist")


def test_unreadable_image_among_good_ones_is_skipped(runner, cli_app, data, tmp_path):
    folder = Path(shutil.copytree(data["queries"], tmp_path / "q"))
    (folder / "q3.png").write_bytes(b"")
    result = runner.invoke(cli_app, ["localize", str(data["map"]), str(folder), "--json"])
    rows = ok_json(result)
    assert "q3.png" not in [r["query"] for r in rows] and len(rows) == len(QUERIES)
    assert "skipped q3.png" in result.stderr


def test_empty_query_folder(runner, cli_app, data, tmp_path):
    (tmp_path / "empty").mkdir()
    assert_error(runner.invoke(cli_app, ["localize", str(data["map"]), str(tmp_path / "empty")]), "is empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.png").write_bytes(b"")
    assert_error(runner.invoke(cli_app, ["eval", str(data["map"]), str(tmp_path / "junk"), "--ground-truth", "same-name"]),
                 "no query file name is a frame of the map")


def test_map_without_index(runner, cli_app, data, tmp_path):
    bare = Path(shutil.copy(data["map"], tmp_path / "bare.topomap"))
    tamper(bare, "DELETE FROM array")
    reseal(bare)  # an index-less map as `--no-index` or an older topomap wrote it
    for extra in (["--descriptor", "fused"], ["--descriptor", "bow"]):
        assert_error(runner.invoke(cli_app, ["localize", str(bare), str(data["queries"]), *extra]),
                     "no place-recognition index", "topomap index MAP")
    rows = ok_json(runner.invoke(cli_app, ["localize", str(bare), str(data["queries"]), "--descriptor", "thumbnail", "--json"]))
    assert len(rows) == len(QUERIES)


def test_feature_type_of_the_map(runner, cli_app, data, tmp_path):
    sift_map = tmp_path / "sift.topomap"
    result = runner.invoke(cli_app, ["build", str(data["root"] / "map"), "-o", str(sift_map), "--features", "sift",
                                     "--max-features", "200"])
    assert result.exit_code == 0, result.output
    query = str(data["queries"] / "q2.png")
    assert_error(runner.invoke(cli_app, ["localize", str(sift_map), query, "--features", "orb"]),
                 "built with sift features", "--features sift")
    assert_error(runner.invoke(cli_app, ["localize", str(data["map"]), query, "--features", "surf"]),
                 "unknown feature type 'surf'", "akaze, orb, sift")
    rows = ok_json(runner.invoke(cli_app, ["localize", str(sift_map), query, "--features", "SIFT", "--json"]))
    assert set(rows[0]["frames"]) & right_frames(2)


def test_ground_truth_naming_frames_not_in_the_map(runner, cli_app, data, tmp_path):
    gt = tmp_path / "gt.csv"
    gt.write_text("query_file,matching_ref_indices\nq2.png,1;2;300\nq5.png,301;302\nq8.png,303\n")
    assert_error(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), "--ground-truth", str(gt)]),
                 "not in the map", "300, 301, 302", "16 frames")
    gt.write_text("query_file,matching_ref_files\nq2.png,img2.png;ghost_a.png\nq5.png,ghost_b.png\n")
    assert_error(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), "--ground-truth", str(gt)]),
                 "names 2 frame(s) that are not in the map", "ghost_a.png, ghost_b.png")
    gt.write_text("query_file,matching_ref_indices\nother.png,1\n")
    assert_error(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), "--ground-truth", str(gt)]),
                 "names none of the queries")


@pytest.mark.parametrize("args, fragments", [
    (["--ground-truth", "{query_poses}", "--map-poses", "{map_poses}"], ["needs both --map-poses and --radius"]),
    (["--ground-truth", "{query_poses}", "--map-poses", "{map_poses}", "--radius", "-1"], ["--radius must be positive"]),
    (["--ground-truth", "{root}/none.csv"], ["does not exist"]),
    (["--ground-truth", "{map_poses}"], ["not a correspondence CSV"]),
    (["--ground-truth", "{gt}", "--plot", "{root}/no/such/folder/pr.png"], ["does not exist", "--plot"]),
    (["--ground-truth", "{gt}", "--descriptor", "colour"], ["unknown descriptor 'colour'", "auto, bow, fused, hog, thumbnail"]),
])
def test_bad_eval_options(runner, cli_app, data, args, fragments):
    args = [a.format(**data) for a in args]
    assert_error(runner.invoke(cli_app, ["eval", str(data["map"]), str(data["queries"]), *args]), *fragments)


def test_not_a_map(runner, cli_app, data, tmp_path):
    assert_error(runner.invoke(cli_app, ["localize", str(tmp_path / "none.topomap"), str(data["queries"])]),
                 "does not exist")
    assert_error(runner.invoke(cli_app, ["localize", str(data["queries"] / "q2.png"), str(data["queries"])]))


# ============================================================================= real data: corridor
@pytest.mark.slow
def test_corridor_eval_sequence(runner, cli_app, tmp_path_factory):
    """Issue 3 through the CLI: corridor ground-truth CSV, sequence mode, Recall@1 >= 0.75."""
    root = dataset("corridor")
    d = ok_json(runner.invoke(cli_app, ["eval", str(corridor_map_file(tmp_path_factory)), str(root / "query"),
                                        "--ground-truth", str(root / "ground_truth.csv"), "--sequence", "--json"]))
    assert d["queries"] == d["queries_with_match"] == 111 and d["skipped"] == []
    assert d["recall_at_1"] >= 0.75 and d["recall_at_10"] >= 0.95 and d["auc"] > 0.6, d
