"""`topomap build | info | show | export | index` through typer's CliRunner: every bad input of
issue 2 (one "Error:" line, exit 1, no traceback), safe writes, round trips, inputs and cameras."""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

import cv2
import networkx as nx
import numpy as np
import pytest
from conftest import assert_error, corridor_map_file, dataset, tamper
from fuzz_cases import reseal
from map_synth import FRAME_SIZE, SHORT_WALK_PX, out_and_back_x, scene, sequence, window, write_out_and_back, write_sequence, write_video
from typer.testing import CliRunner

import topomap.build as build_mod
import topomap.store as store
from topomap.store import SCHEMA_VERSION, load_map

#: Options that keep synthetic CLI builds quick (few features: a small vocabulary).
QUICK = ["--max-features", "300"]


def ok(result):
    assert result.exit_code == 0, result.output
    assert result.exception is None and "Traceback" not in result.output
    return result


def build_json(runner, app, *args) -> dict:
    """Run `topomap build ... --json` and return the summary."""
    return json.loads(ok(runner.invoke(app, ["build", *map(str, args), "--json"])).stdout)


def info_json(runner, app, path) -> dict:
    return json.loads(ok(runner.invoke(app, ["info", str(path), "--json"])).stdout)


def files_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def interrupt(*args, **kwargs):
    raise KeyboardInterrupt


#: Window positions of the walk: the short one (several tests build it again, some three times).
WALK_X = out_and_back_x(length_px=SHORT_WALK_PX)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """(image folder, map path) of the short synthetic out-and-back walk, built once through the CLI."""
    from topomap_cli.main import app

    root = tmp_path_factory.mktemp("cliwalk")
    write_out_and_back(root / "imgs", length_px=SHORT_WALK_PX)
    result = CliRunner().invoke(app, ["build", str(root / "imgs"), "-o", str(root / "walk.topomap"), *QUICK])
    ok(result)
    return root / "imgs", root / "walk.topomap"


@pytest.fixture
def walk_copy(walk, tmp_path):
    return Path(shutil.copy(walk[1], tmp_path / "copy.topomap"))


@pytest.fixture(scope="module")
def two_frames(tmp_path_factory):
    """Two 8-bit frames of the synthetic scene, 30 px apart."""
    return sequence(2, step_px=30.0)


# ============================================================================= bad input (issue 2)
def test_missing_path(runner, cli_app, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "nowhere"), "-o", str(tmp_path / "m.topomap")]),
                 "nowhere does not exist")
    assert files_in(tmp_path) == []


def test_empty_folder(runner, cli_app, tmp_path):
    (tmp_path / "empty").mkdir()
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "empty"), "-o", str(tmp_path / "m.topomap")]),
                 "is empty")
    assert files_in(tmp_path) == ["empty"]


def test_folder_with_no_images(runner, cli_app, tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "notes.txt").write_text("hello")
    (tmp_path / "docs" / "data.csv").write_text("a,b\n")
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "docs"), "-o", str(tmp_path / "m.topomap")]),
                 "holds no images", "jpg", "png")


@pytest.mark.parametrize("damage", ["corrupt", "truncated", "zero-byte", "text"])
def test_bad_image_among_good_ones_is_skipped(runner, cli_app, tmp_path, damage):
    write_sequence(tmp_path / "imgs", sequence(4), ext=".jpg")
    bad = tmp_path / "imgs" / "img2.jpg"
    data = bad.read_bytes()
    bad.write_bytes({"corrupt": data[:200] + bytes(range(256)) * 40, "truncated": data[: len(data) // 2],
                     "zero-byte": b"", "text": b"not an image at all"}[damage])
    result = ok(runner.invoke(cli_app, ["build", str(tmp_path / "imgs"), "-o", str(tmp_path / "m.topomap"), *QUICK,
                                        "--json"]))
    summary = json.loads(result.stdout)
    assert summary["frames_read"] == 3 and summary["frames_skipped"] == 1
    assert summary["skipped"][0]["frame"] == "img2.jpg"
    assert "warning:" in result.stderr and "skipped img2.jpg" in result.stderr
    m = load_map(tmp_path / "m.topomap")
    assert [f.status for f in m.frames] == ["ok", "ok", "unreadable", "ok"] and m.frames[2].node is None


def test_zero_byte_file(runner, cli_app, tmp_path):
    (tmp_path / "z.jpg").write_bytes(b"")
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "z.jpg"), "-o", str(tmp_path / "m.topomap")]),
                 "no usable image", "empty file", alone=False)
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "z.png").write_bytes(b"")
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "dir"), "-o", str(tmp_path / "m.topomap")]),
                 "no usable image", "z.png", "empty file", alone=False)
    assert not (tmp_path / "m.topomap").exists()


def test_non_image_with_image_extension(runner, cli_app, tmp_path):
    (tmp_path / "photo.png").write_text("I am a text file pretending to be a PNG")
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "photo.png"), "-o", str(tmp_path / "m.topomap")]),
                 "photo.png", "not a readable image", alone=False)


def test_unreadable_or_empty_video(runner, cli_app, tmp_path):
    (tmp_path / "junk.avi").write_bytes(b"RIFF" + bytes(200))
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "junk.avi"), "-o", str(tmp_path / "m.topomap")]),
                 "cannot open video junk.avi")
    vw = cv2.VideoWriter(str(tmp_path / "none.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    vw.release()  # a valid container without frames
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "none.avi"), "-o", str(tmp_path / "m.topomap")]),
                 "no usable image", "holds no frames", alone=False)
    assert not (tmp_path / "m.topomap").exists()


def test_single_image(runner, cli_app, tmp_path, two_frames):
    cv2.imwrite(str(tmp_path / "only.png"), two_frames[0])
    s = build_json(runner, cli_app, tmp_path / "only.png", "-o", tmp_path / "m.topomap", *QUICK)
    assert (s["frames_read"], s["nodes"], s["edges"], s["components"]) == (1, 1, 0, 1)
    assert info_json(runner, cli_app, tmp_path / "m.topomap")["nodes"] == 1


def test_identical_repeated_frames(runner, cli_app, tmp_path, two_frames):
    write_sequence(tmp_path / "same", [two_frames[0]] * 6)
    s = build_json(runner, cli_app, tmp_path / "same", "-o", tmp_path / "m.topomap", *QUICK)
    assert (s["frames_read"], s["nodes"], s["edges"]) == (6, 1, 0)
    data = json.loads(ok(runner.invoke(cli_app, ["export", str(tmp_path / "m.topomap"), "-o", str(tmp_path / "m.json")]))
                      and (tmp_path / "m.json").read_text())
    assert data["nodes"][0]["frames"] == [f"img{i}.png" for i in range(6)]


def test_tiny_image(runner, cli_app, tmp_path, two_frames):
    (tmp_path / "tiny").mkdir()
    cv2.imwrite(str(tmp_path / "tiny" / "t.png"), two_frames[0][:16, :16])
    assert_error(runner.invoke(cli_app, ["build", str(tmp_path / "tiny"), "-o", str(tmp_path / "m.topomap")]),
                 "no usable image", "16x16 px is too small", alone=False)
    assert not (tmp_path / "m.topomap").exists()


def test_16bit_png(runner, cli_app, tmp_path, two_frames):
    write_sequence(tmp_path / "u8", two_frames)
    write_sequence(tmp_path / "u16", [f.astype(np.uint16) * 257 for f in two_frames])
    assert cv2.imread(str(tmp_path / "u16" / "img0.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    build_json(runner, cli_app, tmp_path / "u8", "-o", tmp_path / "u8.topomap", *QUICK)
    s = build_json(runner, cli_app, tmp_path / "u16", "-o", tmp_path / "u16.topomap", *QUICK)
    assert s["frames_read"] == 2 and s["frames_skipped"] == 0
    a, b = load_map(tmp_path / "u8.topomap"), load_map(tmp_path / "u16.topomap")
    assert len(b.nodes[0].features) == 300  # the 16-bit image was read at full contrast
    assert b.nodes[0].features.descriptors.tobytes() == a.nodes[0].features.descriptors.tobytes()


def test_rgba_png(runner, cli_app, tmp_path, two_frames):
    write_sequence(tmp_path / "grey", two_frames)
    rgba = [np.dstack([cv2.cvtColor(f, cv2.COLOR_GRAY2BGR), np.full_like(f, 128)]) for f in two_frames]
    write_sequence(tmp_path / "rgba", rgba)
    assert cv2.imread(str(tmp_path / "rgba" / "img0.png"), cv2.IMREAD_UNCHANGED).shape[2] == 4
    build_json(runner, cli_app, tmp_path / "grey", "-o", tmp_path / "g.topomap", *QUICK)
    s = build_json(runner, cli_app, tmp_path / "rgba", "-o", tmp_path / "c.topomap", *QUICK)
    assert s["frames_read"] == 2 and s["frames_skipped"] == 0
    a, b = load_map(tmp_path / "g.topomap"), load_map(tmp_path / "c.topomap")
    assert b.nodes[0].features.keypoints.tobytes() == a.nodes[0].features.keypoints.tobytes()


def test_unknown_features_lists_choices(runner, cli_app, walk, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "m.topomap"), "--features", "surf"]),
                 "unknown feature type 'surf'", "akaze, orb, sift")
    assert files_in(tmp_path) == []


def test_unknown_preset_lists_choices(runner, cli_app, walk, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "m.topomap"), "--preset", "x"]),
                 "unknown build preset 'x'", "accurate, default, dense, fast")


def test_existing_output_without_force(runner, cli_app, walk, walk_copy):
    before = walk_copy.read_bytes()
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy)]),
                 "already exists", "--force", "--append")
    assert walk_copy.read_bytes() == before
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy), "--force", "--append"]),
                 "--append and --force exclude each other")
    assert walk_copy.read_bytes() == before


def test_output_in_missing_folder(runner, cli_app, walk, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "no" / "such" / "m.topomap")]),
                 "does not exist", "create it first")
    assert files_in(tmp_path) == []


def test_output_is_a_folder(runner, cli_app, walk, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path)]), "is a folder")


def test_bad_option_values(runner, cli_app, walk, tmp_path):
    out = str(tmp_path / "m.topomap")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", out, "--every", "0"]), "--every")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", out, "--max-features", "2"]), "max_features")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", out, "--resize", "10"]), "resize_max_px")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", out, "--camera", str(tmp_path / "c.yaml")]),
                 "camera file", "does not exist")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", out, "--max-features", "many"]),
                 "Invalid value for '--max-features'")
    assert_error(runner.invoke(cli_app, ["build", str(walk[0])]), "Missing option")
    assert files_in(tmp_path) == []


# ============================================================================= map files given to info
def test_truncated_map(runner, cli_app, walk_copy):
    data = walk_copy.read_bytes()
    walk_copy.write_bytes(data[: len(data) // 3])
    assert_error(runner.invoke(cli_app, ["info", str(walk_copy)]), "copy.topomap", "rebuild it")


@pytest.mark.parametrize("links", [[[0, 10_000]], [[0, 1]]], ids=["unknown node", "one experience"])
def test_a_strangers_aligned_links_are_refused_in_one_line(runner, cli_app, walk_copy, links):
    m = load_map(walk_copy, images=True)
    m.arrays["aligned_links"] = np.array(links, np.int64)
    m.arrays["aligned_confidence"] = np.full(len(links), 0.99, np.float32)
    store.save_map(m, walk_copy, overwrite=True)
    before = walk_copy.read_bytes()
    for command in (["info", str(walk_copy)], ["localize", str(walk_copy), str(dataset("corridor") / "query")]):
        assert_error(runner.invoke(cli_app, command), "aligned link", "rebuild the map")
    assert walk_copy.read_bytes() == before


def test_foreign_png(runner, cli_app, tmp_path, two_frames):
    cv2.imwrite(str(tmp_path / "pic.png"), two_frames[0])
    assert_error(runner.invoke(cli_app, ["info", str(tmp_path / "pic.png")]), "not a topomap map file")


def test_foreign_sqlite(runner, cli_app, tmp_path):
    con = sqlite3.connect(tmp_path / "shop.db")
    con.executescript("CREATE TABLE item (name TEXT, price REAL); INSERT INTO item VALUES ('tea', 2.5);")
    con.close()
    assert_error(runner.invoke(cli_app, ["info", str(tmp_path / "shop.db")]), "SQLite database but not a topomap map")


def test_newer_schema(runner, cli_app, walk_copy):
    tamper(walk_copy, f"PRAGMA user_version = {SCHEMA_VERSION + 5}")
    assert_error(runner.invoke(cli_app, ["info", str(walk_copy)]), "newer topomap", "upgrade topomap")
    for cmd in (["show", str(walk_copy), "-o", str(walk_copy.parent / "g.png")],
                ["export", str(walk_copy), "-o", str(walk_copy.parent / "g.json")],
                ["index", str(walk_copy)]):
        assert_error(runner.invoke(cli_app, cmd), "upgrade topomap")


def test_missing_map(runner, cli_app, tmp_path):
    assert_error(runner.invoke(cli_app, ["info", str(tmp_path / "none.topomap")]), "does not exist", "topomap build")


# ============================================================================= safe writes
def test_interrupted_build_leaves_no_file(runner, cli_app, walk, tmp_path, monkeypatch):
    monkeypatch.setattr(build_mod, "_close_loops", interrupt)
    result = runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "m.topomap"), *QUICK])
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert files_in(tmp_path) == []


@pytest.mark.parametrize("where", ["loops", "save"])
def test_interrupted_rebuild_keeps_the_existing_map(runner, cli_app, walk, walk_copy, monkeypatch, where):
    before = walk_copy.read_bytes()
    if where == "loops":
        monkeypatch.setattr(build_mod, "_close_loops", interrupt)
    else:  # after the node rows went into the temporary file
        monkeypatch.setattr(store, "_frame_rows", interrupt)
    result = runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy), "--force", *QUICK])
    assert result.exit_code != 0
    assert walk_copy.read_bytes() == before
    assert files_in(walk_copy.parent) == ["copy.topomap"]  # no temporary or journal file


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_failed_append_keeps_the_map(runner, cli_app, walk, walk_copy, monkeypatch):
    before = walk_copy.read_bytes()
    monkeypatch.setattr(store, "_edge_rows", interrupt)  # midway: new nodes and frames already inserted
    result = runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy), "--append"])
    assert result.exit_code != 0
    assert walk_copy.read_bytes() == before
    assert files_in(walk_copy.parent) == ["copy.topomap"]
    monkeypatch.undo()
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy.parent / "new.topomap"), "--append"]),
                 "new.topomap does not exist", "build it first")


# ============================================================================= round trips
def test_build_summary_and_info(runner, cli_app, walk):
    folder, path = walk
    text = ok(runner.invoke(cli_app, ["info", str(path)])).stdout
    for word in ("nodes", "edges", "components", "schema version", "sequential", "loop"):
        assert word in text
    data = info_json(runner, cli_app, path)
    assert {"nodes", "frames", "edges", "edges_by_kind", "components", "features", "schema_version"} <= set(data)
    assert data["schema_version"] == SCHEMA_VERSION and data["frames"] == len(WALK_X)
    assert data["edges_by_kind"]["loop"] >= 1 and data["components"] == 1
    assert data["features"]["kind"] == "orb" and data["build_config"]["features"]["max_features"] == 300
    m = load_map(path)
    assert (data["nodes"], data["edges"]) == (len(m.nodes), len(m.edges))
    assert data["camera"]["source"] == "default"  # the default intrinsics are recorded
    assert data["camera"]["fx"] == pytest.approx((FRAME_SIZE[0] / 2) / np.tan(np.radians(30)))


def test_build_text_summary(runner, cli_app, tmp_path, two_frames):
    write_sequence(tmp_path / "imgs", two_frames)
    result = ok(runner.invoke(cli_app, ["build", str(tmp_path / "imgs"), "-o", str(tmp_path / "m.topomap"), *QUICK]))
    for word in ("frames read", "nodes", "edges", "sequential", "time", "frames/s"):
        assert word in result.stdout
    assert "frames" in result.stderr  # the progress bar


def test_export_json(runner, cli_app, walk, tmp_path):
    ok(runner.invoke(cli_app, ["export", str(walk[1]), "--format", "json", "-o", str(tmp_path / "m.json")]))
    data = json.loads((tmp_path / "m.json").read_text())
    m = load_map(walk[1])
    assert [n["id"] for n in data["nodes"]] == sorted(m.nodes)
    for n in data["nodes"]:
        assert {"id", "keyframe", "frames"} <= set(n) and n["keyframe"] == m.nodes[n["id"]].source
        assert n["keyframe"] in n["frames"]
    names = [f for n in data["nodes"] for f in n["frames"]]
    assert names == [f"img{i}.png" for i in range(len(WALK_X))]  # every frame once, natural order
    assert len(data["edges"]) == len(m.edges)
    for e in data["edges"]:
        assert {"source", "target", "kind", "inliers"} <= set(e)
        assert e["kind"] == m.edge(e["source"], e["target"]).kind.value


def test_export_graphml(runner, cli_app, walk, tmp_path):
    ok(runner.invoke(cli_app, ["export", str(walk[1]), "--format", "graphml", "-o", str(tmp_path / "m.graphml")]))
    g = nx.read_graphml(tmp_path / "m.graphml", node_type=int)
    m = load_map(walk[1])
    assert sorted(g.nodes) == sorted(m.nodes) and g.number_of_edges() == len(m.edges)
    assert {d["kind"] for _, _, d in g.edges(data=True)} == {"sequential", "loop"}
    assert_error(runner.invoke(cli_app, ["export", str(walk[1]), "--format", "csv", "-o", str(tmp_path / "m.csv")]),
                 "unknown format 'csv'", "graphml, json")
    assert_error(runner.invoke(cli_app, ["export", str(walk[1]), "-o", str(tmp_path / "no" / "m.json")]),
                 "does not exist")


def test_show_with_and_without_poses(runner, cli_app, walk, tmp_path):
    ok(runner.invoke(cli_app, ["show", str(walk[1]), "-o", str(tmp_path / "g.png")]))
    plain = cv2.imread(str(tmp_path / "g.png"))
    assert plain is not None and plain.std() > 5
    poses = tmp_path / "poses.csv"
    poses.write_text("image,x,z,theta\n" + "".join(f"img{i}.png,{x / 100:.2f},{0.1 * (i % 2):.1f},0\n"
                                                   for i, x in enumerate(WALK_X)))
    ok(runner.invoke(cli_app, ["show", str(walk[1]), "-o", str(tmp_path / "gt.png"), "--poses", str(poses)]))
    gt = cv2.imread(str(tmp_path / "gt.png"))
    assert gt is not None and gt.shape == plain.shape and not np.array_equal(gt, plain)
    poses.write_text("image,x,z\nother.png,0,0\n")
    assert_error(runner.invoke(cli_app, ["show", str(walk[1]), "-o", str(tmp_path / "x.png"), "--poses", str(poses)]),
                 "has no pose for keyframe")
    assert_error(runner.invoke(cli_app, ["show", str(walk[1]), "-o", str(tmp_path / "no" / "x.png")]), "does not exist")


def test_show_and_export_output_paths(runner, cli_app, walk, tmp_path, monkeypatch):
    m = str(walk[1])
    (tmp_path / "out").mkdir()
    for cmd in (["show", m, "-o", str(tmp_path / "out")], ["export", m, "-o", str(tmp_path / "out")],
                ["export", m, "--format", "graphml", "-o", str(tmp_path / "out")]):
        assert_error(runner.invoke(cli_app, cmd), "is a folder")
    for name in ("graph.foo", "graph"):  # matplotlib would append .png or fail on an unknown type
        assert_error(runner.invoke(cli_app, ["show", m, "-o", str(tmp_path / name)]), f"cannot write {name}", ".png")
    ok(runner.invoke(cli_app, ["show", m, "-o", str(tmp_path / "graph.svg")]))
    assert (tmp_path / "graph.svg").read_text().lstrip().startswith("<?xml")
    assert files_in(tmp_path) == ["graph.svg", "out"]

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    import topomap.viz

    monkeypatch.setattr(topomap.viz, "plot_map", denied)
    assert_error(runner.invoke(cli_app, ["show", m, "-o", str(tmp_path / "g.png")]), "cannot write", "Permission denied")
    monkeypatch.setattr(Path, "write_text", denied)
    assert_error(runner.invoke(cli_app, ["export", m, "-o", str(tmp_path / "g.json")]), "cannot write", "Permission denied")


def test_index_rebuilds_the_index(runner, cli_app, walk, walk_copy):
    original = load_map(walk[1]).index.to_arrays()
    tamper(walk_copy, "DELETE FROM array")
    reseal(walk_copy)  # an index-less map as an older topomap wrote it
    assert info_json(runner, cli_app, walk_copy)["index"] is False
    result = ok(runner.invoke(cli_app, ["index", str(walk_copy)]))
    assert "indexed" in result.stdout
    assert info_json(runner, cli_app, walk_copy)["index"] is True
    rebuilt = load_map(walk_copy).index.to_arrays()
    assert rebuilt.keys() == original.keys() and all(np.array_equal(rebuilt[k], original[k]) for k in original)


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_append_adds_and_links_a_sequence(runner, cli_app, tmp_path):
    tex = scene(4)
    rng = np.random.default_rng(1)
    xs = range(0, 480, 60)  # 8 frames a pass: several keyframes each, one frame width of wall
    write_sequence(tmp_path / "first", [window(tex, x, y=40.0) for x in xs])
    write_sequence(tmp_path / "second", [np.clip(window(tex, x + 5, y=55.0) + rng.normal(0, 4, FRAME_SIZE[::-1]), 0, 255)
                                         .astype(np.uint8) for x in xs], stem="pass2_")
    path = tmp_path / "m.topomap"
    first = build_json(runner, cli_app, tmp_path / "first", "-o", path, *QUICK)
    s = build_json(runner, cli_app, tmp_path / "second", "-o", path, "--append")
    assert s["frames"] == 2 * len(xs) and s["nodes"] == first["nodes"] + s["nodes_added"] and s["nodes_added"] >= 2
    assert s["components"] == 1
    m = load_map(path)
    assert len(m.sequences) == 2 and {n.sequence for n in m.nodes.values()} == {0, 1}
    links = [e for e in m.edges.values() if m.nodes[e.a].sequence != m.nodes[e.b].sequence]
    assert links and all(e.kind.value == "loop" for e in links)
    assert m.config.features.max_features == 300  # the map keeps its own config
    assert info_json(runner, cli_app, path)["sequences"] == 2


def test_append_with_other_features_is_refused(runner, cli_app, walk, walk_copy):
    before = walk_copy.read_bytes()
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy), "--append", "-f", "sift"]),
                 "uses orb features", "cannot append", alone=False)
    assert walk_copy.read_bytes() == before


# ============================================================================= inputs and cameras
def test_natural_sort(runner, cli_app, tmp_path):
    frames = sequence(12, step_px=25.0)
    write_sequence(tmp_path / "imgs", frames)  # img0 .. img11: lexical order would put img10 after img1
    ok(runner.invoke(cli_app, ["build", str(tmp_path / "imgs"), "-o", str(tmp_path / "m.topomap"), *QUICK]))
    m = load_map(tmp_path / "m.topomap")
    assert [f.source for f in m.frames] == [f"img{i}.png" for i in range(12)]
    assert [f.index for f in m.frames] == list(range(12))


def test_video_every_2(runner, cli_app, tmp_path):
    video = write_video(tmp_path / "walk.avi", sequence(10, step_px=25.0))
    full = build_json(runner, cli_app, video, "-o", tmp_path / "a.topomap", *QUICK)
    half = build_json(runner, cli_app, video, "-o", tmp_path / "b.topomap", "--every", "2", *QUICK)
    assert (full["frames"], half["frames"]) == (10, 5)
    assert [f.source for f in load_map(tmp_path / "b.topomap").frames] == [f"frame_{i:06d}" for i in range(0, 10, 2)]


def test_list_file_input(runner, cli_app, tmp_path):
    write_sequence(tmp_path / "imgs", sequence(4, step_px=30.0))
    (tmp_path / "frames.txt").write_text("# chosen frames\nimgs/img3.png\nimgs/img1.png\n")
    s = build_json(runner, cli_app, tmp_path / "frames.txt", "-o", tmp_path / "m.topomap", *QUICK)
    assert s["frames"] == 2
    assert [f.source for f in load_map(tmp_path / "m.topomap").frames] == ["img3.png", "img1.png"]


@pytest.mark.parametrize("fmt", ["yaml", "json", "K.txt"])
def test_camera_files(runner, cli_app, tmp_path, two_frames, fmt):
    write_sequence(tmp_path / "imgs", two_frames)
    if fmt == "K.txt":
        cam = Path(shutil.copy(dataset("castle-p30") / "K.txt", tmp_path / "K.txt"))  # castle's intrinsics
        expected = (689.87, 691.04, 380.1725, 251.7025, "K.txt")
    else:
        cam = tmp_path / f"cam.{fmt}"
        d = {"fx": 400.0, "fy": 402.0, "cx": 240.0, "cy": 180.0, "width": 480, "height": 360}
        cam.write_text(json.dumps(d) if fmt == "json" else "\n".join(f"{k}: {v}" for k, v in d.items()) + "\n")
        expected = (400.0, 402.0, 240.0, 180.0, cam.name)
    ok(runner.invoke(cli_app, ["build", str(tmp_path / "imgs"), "-o", str(tmp_path / "m.topomap"), "--camera", str(cam),
                               *QUICK]))
    c = info_json(runner, cli_app, tmp_path / "m.topomap")["camera"]
    assert (c["fx"], c["fy"], c["cx"], c["cy"], c["source"]) == pytest.approx(expected)


def test_camera_scales_with_resize(runner, cli_app, tmp_path, two_frames):
    write_sequence(tmp_path / "imgs", two_frames)
    (tmp_path / "cam.yaml").write_text("fx: 400\nfy: 400\ncx: 239.5\ncy: 179.5\nwidth: 480\nheight: 360\n")
    ok(runner.invoke(cli_app, ["build", str(tmp_path / "imgs"), "-o", str(tmp_path / "m.topomap"), "--camera",
                               str(tmp_path / "cam.yaml"), "--resize", "240", "--preset", "fast"]))
    m = load_map(tmp_path / "m.topomap")
    assert m.working_size == (240, 180) and m.camera.fx == 200.0 and m.camera.cx == pytest.approx(119.5)
    assert m.config.features.resize_max_px == 240 and m.config.features.max_features == 500  # fast preset


# ============================================================================= issue 14: hostile input
def test_index_of_a_read_only_map_says_so(runner, cli_app, walk_copy, monkeypatch):
    import topomap.store as store_mod

    monkeypatch.setattr(store_mod.os, "access", lambda p, mode: mode != store_mod.os.W_OK)
    assert_error(runner.invoke(cli_app, ["index", str(walk_copy)]), "is read-only", "copy it somewhere writable")


@pytest.mark.parametrize("value", ["99999999999999999999", "1000000000"])
def test_absurd_max_features_is_one_line(runner, cli_app, walk, tmp_path, value):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "m.topomap"), "--max-features", value]),
                 "is too large; use at most 100000")


def test_camera_folder_is_named_a_folder(runner, cli_app, walk, tmp_path):
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(tmp_path / "m.topomap"), "--camera", str(tmp_path)]),
                 "is a folder")


def test_bomb_and_odd_entries_in_a_build_folder_are_skipped_and_counted(runner, cli_app, two_frames, tmp_path):
    from fuzz_cases import pgm_declaring, png_bomb

    folder = tmp_path / "frames"
    write_sequence(folder, two_frames, stem="f")
    (folder / "a0_bomb.png").write_bytes(png_bomb(30000, 30000))  # first in order: it must not set the working size
    (folder / "a1_bomb.pgm").write_bytes(pgm_declaring(40000, 40000))
    (folder / "x.jpg").mkdir()
    (folder / "caf\udce9.png").write_bytes((folder / "f0.png").read_bytes())
    s = build_json(runner, cli_app, folder, "-o", tmp_path / "m.topomap", *QUICK)
    reasons = {x["frame"]: x["reason"] for x in s["skipped"]}
    assert s["frames_read"] == 3 and s["frames_skipped"] == 3, s
    assert "declares 30000x30000 pixels" in reasons["a0_bomb.png"] and "is a folder" in reasons["x.jpg"]
    m = load_map(tmp_path / "m.topomap")
    assert m.working_size == (480, 360) and "caf\\xe9.png" in [f.source for f in m.frames]


# ============================================================================= workers, Dask, compact maps (issue 17)
def map_contents(path: Path) -> dict:
    """Every row of a map file but the header lines that record when and how fast it was built."""
    con = sqlite3.connect(path)
    try:
        rows = {t: con.execute(f"SELECT * FROM {t} ORDER BY 1, 2").fetchall() for t in ("node", "feature", "edge", "frame", "array")}
        meta = {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
    finally:
        con.close()
    for k in ("created_utc", "modified_utc"):
        meta.pop(k)
    for s in meta["sequences"]:
        s.pop("seconds")
    return {**rows, "meta": meta}


@pytest.mark.parametrize("args, fragment", [
    (["--workers", "0"], "--workers must be at least 1, got 0"),
    (["--workers", "-3"], "--workers must be at least 1"),
    (["--dask", "cloud"], "--dask takes 'local'"),
    (["--dask", "local", "--scheduler", "tcp://127.0.0.1:9"], "exclude each other"),
    (["--scheduler", "tcp://127.0.0.1:9"], "cannot reach the Dask scheduler at tcp://127.0.0.1:9"),
    (["--scheduler", "127.0.0.1"], "not a tcp://HOST:PORT address"),
    (["--image-quality", "0"], "image_quality=0 must lie in 1..100"),
])
def test_bad_worker_and_image_options(runner, cli_app, walk, tmp_path, args, fragment):
    out = tmp_path / "m.topomap"
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(out), *QUICK, *args]), fragment)
    assert files_in(tmp_path) == []  # no half map


def test_unreachable_scheduler_keeps_an_existing_map(runner, cli_app, walk, walk_copy):
    before = walk_copy.read_bytes()
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(walk_copy), "--force", *QUICK,
                                         "--scheduler", "tcp://127.0.0.1:9"]), "cannot reach")
    assert walk_copy.read_bytes() == before


@pytest.fixture(scope="module")
def scheduler():
    """The address of a small Dask cluster whose workers are threads of this process."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1",
                      dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


@pytest.mark.slow
def test_workers_and_scheduler_build_the_same_map(runner, cli_app, walk, scheduler, tmp_path):
    maps = {}
    for name, args in (("one", ["--workers", "1"]), ("two", ["--workers", "2"]), ("dask", ["--scheduler", scheduler])):
        summary = build_json(runner, cli_app, walk[0], "-o", tmp_path / f"{name}.topomap", *QUICK, *args)
        assert ("dask" in summary["workers"]) == (name == "dask")
        maps[name] = map_contents(tmp_path / f"{name}.topomap")
    assert len(maps["one"]["node"]) >= 3
    assert maps["two"] == maps["one"] and maps["dask"] == maps["one"]


def test_a_worker_that_cannot_read_the_images(runner, cli_app, walk, scheduler, tmp_path, monkeypatch):
    """Workers that do not see the images at this machine's paths: one line, exit 1, no map."""
    def blind(task):
        if task.image is not None:
            return task.image, None, False
        return None, f"image {task.path} does not exist", True

    monkeypatch.setattr(build_mod, "_decode", blind)  # the workers are threads of this process
    out = tmp_path / "m.topomap"
    assert_error(runner.invoke(cli_app, ["build", str(walk[0]), "-o", str(out), *QUICK, "--scheduler", scheduler]),
                 "a Dask worker cannot read", "same path", alone=False)
    assert files_in(tmp_path) == []


@pytest.mark.slow
def test_dask_local_cluster_builds_the_same_map(runner, cli_app, walk, tmp_path):
    one = build_json(runner, cli_app, walk[0], "-o", tmp_path / "one.topomap", *QUICK, "--workers", "1")
    dask = build_json(runner, cli_app, walk[0], "-o", tmp_path / "dask.topomap", *QUICK, "--dask", "local", "--workers", "2")
    assert "dask" in dask["workers"] and dask["nodes"] == one["nodes"]
    assert map_contents(tmp_path / "dask.topomap") == map_contents(tmp_path / "one.topomap")


@pytest.mark.slow  # builds one or more maps end to end (~8-30 s)
def test_no_images_and_image_quality(runner, cli_app, walk, tmp_path):
    full = build_json(runner, cli_app, walk[0], "-o", tmp_path / "full.topomap", *QUICK, "--workers", "1")
    bare = build_json(runner, cli_app, walk[0], "-o", tmp_path / "bare.topomap", *QUICK, "--workers", "1", "--no-images")
    low = build_json(runner, cli_app, walk[0], "-o", tmp_path / "low.topomap", *QUICK, "--workers", "1", "--image-quality", "20")
    assert bare["nodes"] == full["nodes"] == low["nodes"]
    assert bare["file_bytes"] < low["file_bytes"] < full["file_bytes"]
    con = sqlite3.connect(tmp_path / "bare.topomap")
    assert con.execute("SELECT COUNT(*) FROM node WHERE image IS NOT NULL").fetchone() == (0,)
    assert info_json(runner, cli_app, tmp_path / "low.topomap")["build_config"]["image_quality"] == 20
    # the features, edges and index are the same: only the images differ
    a, b = map_contents(tmp_path / "bare.topomap"), map_contents(tmp_path / "full.topomap")
    assert a["feature"] == b["feature"] and a["edge"] == b["edge"] and a["array"] == b["array"]


@pytest.mark.slow  # 111 labelled queries localized twice (~25 s)
def test_index_calibrates_on_labelled_queries_and_refuses_half_an_option(runner, cli_app, tmp_path, tmp_path_factory):
    root = dataset("corridor")
    # the session's corridor map, built as `topomap build ref -o c.topomap` builds it (the defaults)
    m = Path(shutil.copy(corridor_map_file(tmp_path_factory), tmp_path / "c.topomap"))
    before = m.read_bytes()
    queries, truth = str(root / "query"), str(root / "ground_truth.csv")
    assert_error(runner.invoke(cli_app, ["index", str(m), "--calibrate-on", queries]), "go together")
    assert_error(runner.invoke(cli_app, ["index", str(m), "--calibrate-on", queries, "--ground-truth",
                                         str(tmp_path / "none.csv")]), "does not exist")
    few = tmp_path / "few"
    few.mkdir()
    for name in sorted(p.name for p in (root / "query").iterdir())[:5]:
        shutil.copy(root / "query" / name, few / name)
    assert_error(runner.invoke(cli_app, ["index", str(m), "--calibrate-on", str(few), "--ground-truth", truth]),
                 "5 labelled queries", "need at least 30", "the map is unchanged")
    assert m.read_bytes() == before
    result = ok(runner.invoke(cli_app, ["index", str(m), "--calibrate-on", queries, "--ground-truth", truth]))
    assert "fitted on 111 labelled queries" in result.stdout
    cal = info_json(runner, cli_app, m)["calibration"]
    # the filter answers 6 of the 111 wrong: too few to calibrate its posterior's upper end
    assert cal["fitted_for"]["labelled"] is True and "sequence" not in cal and cal["fitted_for"]["sequence_right"] >= 100
