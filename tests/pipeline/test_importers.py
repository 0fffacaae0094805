"""nerfstudio transforms.json import: poses and pixel directions agree with DESIGN.md."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from panogeom import angles_to_dirs
from pipeline import cli
from runfs.errors import PanoError
from pipeline.importers import (
    import_nerfstudio,
    nerfstudio_to_pose,
    pose_to_nerfstudio,
    sanitize_stem,
    unique_names,
)
from runfs.paths import safe_stem
from schemas.scene_loader import load_scene


def nerfstudio_direction(x_ndc: float, y_ndc: float) -> np.ndarray:
    """nerfstudio's equirectangular ray in its camera frame (OpenGL axes).

    x_ndc in [-1, 1] left to right, y_ndc in [-1/2, 1/2] bottom to top.
    """
    theta = -np.pi * x_ndc
    phi = np.pi * (0.5 - y_ndc)
    return np.array([-np.sin(theta) * np.sin(phi), np.cos(phi), -np.cos(theta) * np.sin(phi)])


@pytest.mark.parametrize("world_up", ["+z", "+y", "-y"])
def test_pose_round_trip(world_up):
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = rng.normal(size=3)
    back = nerfstudio_to_pose(pose_to_nerfstudio(pose, world_up), world_up)
    np.testing.assert_allclose(back, pose, atol=1e-12)


def test_pixel_directions_match_in_world():
    rng = np.random.default_rng(2)
    from scipy.spatial.transform import Rotation

    c2w_gl = np.eye(4)
    c2w_gl[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    ours = nerfstudio_to_pose(c2w_gl, "+z")
    world = {"+z": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])}["+z"]
    for u, v in [(0.5, 0.5), (0.1, 0.3), (0.9, 0.8), (0.25, 0.5)]:  # image fractions, v down
        d_ns = c2w_gl[:3, :3] @ nerfstudio_direction(2 * u - 1, 0.5 - v)
        phi, theta = (u - 0.5) * 2 * np.pi, (0.5 - v) * np.pi
        d_ours = ours[:3, :3] @ angles_to_dirs(phi, theta)
        np.testing.assert_allclose(d_ours, world @ d_ns, atol=1e-12)


def test_import_writes_valid_scene(tiny_scene, tmp_path):
    manifest = json.loads((tiny_scene / "scene.json").read_text())
    frames = [
        {"file_path": v["image"], "transform_matrix": pose_to_nerfstudio(v["pose"]).tolist()}
        for v in manifest["views"]
    ]
    meta = {"camera_model": "EQUIRECTANGULAR", "frames": frames}
    (tiny_scene / "transforms.json").write_text(json.dumps(meta))
    import_nerfstudio(tiny_scene / "transforms.json", tmp_path / "imported", test_every=3)
    scene = load_scene(tmp_path / "imported")
    assert [v.split for v in scene.views] == ["train", "train", "test"]
    assert "pano-pipe import-nerfstudio" in (tmp_path / "imported" / "pano-pipe.yaml").read_text()
    for got, want in zip(scene.views, manifest["views"]):
        np.testing.assert_allclose(got.pose_matrix, want["pose"], atol=1e-12)


def test_import_errors(tmp_path):
    with pytest.raises(PanoError, match="file does not exist"):
        import_nerfstudio(tmp_path / "missing.json", tmp_path / "out")
    (tmp_path / "t.json").write_text(json.dumps({"frames": [{"file_path": "x.png", "transform_matrix": []}]}))
    with pytest.raises(PanoError, match=r"x.png: image missing \(named by frames.0.file_path\)"):
        import_nerfstudio(tmp_path / "t.json", tmp_path / "out")


# --- Hardening: bad input is a one-line error, and nothing is written ----------------------------

IDENTITY = np.eye(4).tolist()


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    """`pano-pipe ARGS` in-process (as tests/pipeline/test_bad_input.py): exit code and output."""
    old = sys.argv
    sys.argv = ["pano-pipe", *args]
    code = 0
    try:
        cli.main()
    except SystemExit as e:
        code = e.code or 0
    finally:
        sys.argv = old
    captured = capsys.readouterr()
    return code, captured.err + captured.out


def snapshot(folder: Path) -> dict[str, bytes] | None:
    """Every file under `folder` with its bytes (None if it does not exist)."""
    if not folder.exists():
        return None
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def source_folder(tmp_path: Path, images: list[str]) -> Path:
    """A folder `src` holding the given (tiny) image files."""
    src = tmp_path / "src"
    for rel in images:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_bytes(b"image " + rel.encode())
    return src


def write_transforms(src: Path, meta) -> Path:
    src.mkdir(parents=True, exist_ok=True)
    path = src / "transforms.json"
    path.write_text(meta if isinstance(meta, str) else json.dumps(meta))
    return path


def frames_for(paths: list[str]) -> list[dict]:
    return [{"file_path": p, "transform_matrix": IDENTITY} for p in paths]


def assert_refused(transforms: Path, out: Path, capsys, *expected: str, args: tuple[str, ...] = ()) -> None:
    """Through the function and the CLI: a PanoError / exit 2 with one line naming what is expected
    (the file first), no traceback, and OUT unchanged (absent if it was)."""
    before = snapshot(out)
    siblings = sorted(p.name for p in out.parent.iterdir()) if out.parent.exists() else None
    with pytest.raises(PanoError) as info:
        kwargs = {}
        if "--test-every" in args:
            kwargs["test_every"] = int(args[args.index("--test-every") + 1])
        if "--world-up" in args:
            kwargs["world_up"] = args[args.index("--world-up") + 1]
        import_nerfstudio(transforms, out, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    for text in expected:
        assert text in message, (text, message)
    code, err = run_cli(["import-nerfstudio", str(transforms), str(out), *args], capsys)
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    for text in expected:
        assert text in err, (text, err)
    assert snapshot(out) == before
    if siblings is not None:  # no temporary folder left beside OUT
        assert sorted(p.name for p in out.parent.iterdir()) == siblings


# 1. file_path must resolve inside the folder holding transforms.json.


@pytest.mark.parametrize(
    "file_path", ["/etc/passwd", "../outside.png", "a/../../outside.png", "..\\outside.png"]
)
def test_file_path_outside_source_is_refused(tmp_path, capsys, file_path):
    (tmp_path / "outside.png").write_bytes(b"secret")
    src = source_folder(tmp_path, ["a/frame.png"])
    t = write_transforms(src, {"frames": frames_for(["a/frame.png", file_path])})
    out = tmp_path / "out"
    assert_refused(t, out, capsys, "transforms.json", "frames.1.file_path")
    assert not out.exists()


def test_symlink_leading_outside_source_is_refused(tmp_path, capsys):
    (tmp_path / "secret.png").write_bytes(b"secret")
    src = source_folder(tmp_path, ["frame.png"])
    os.symlink(tmp_path / "secret.png", src / "link.png")
    os.symlink(tmp_path, src / "up")
    for i, bad in enumerate(["link.png", "up/secret.png"]):
        t = write_transforms(src, {"frames": frames_for(["frame.png", bad])})
        assert_refused(t, tmp_path / f"out{i}", capsys, "transforms.json", "frames.1.file_path", "outside")


def test_symlink_inside_source_is_followed_and_named_as_written(tmp_path):
    src = source_folder(tmp_path, ["blobs/abc123.png"])
    os.symlink(src / "blobs" / "abc123.png", src / "frame.png")
    t = write_transforms(src, {"frames": frames_for(["frame.png"])})
    import_nerfstudio(t, tmp_path / "out", test_every=0)
    scene = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert scene["views"][0]["name"] == "frame"
    copied = tmp_path / "out" / "images" / "frame.png"
    assert not copied.is_symlink() and copied.read_bytes() == b"image blobs/abc123.png"


@pytest.mark.parametrize("file_path", ["loop.png", "loop1/x.png", "x" * 5000, "a/" * 3000 + "x.png"])
def test_unopenable_file_path_is_one_line(tmp_path, capsys, file_path):
    src = source_folder(tmp_path, ["a.png"])
    os.symlink("loop.png", src / "loop.png")
    os.symlink("loop2", src / "loop1")
    os.symlink("loop1", src / "loop2")
    t = write_transforms(src, {"frames": frames_for(["a.png", file_path])})
    assert_refused(t, tmp_path / "out", capsys, "transforms.json", "frames.1.file_path")


# 2. Atomic: a failure half-way leaves nothing; OUT must be new or empty and not overlap the source.


def test_failure_half_way_leaves_nothing(tmp_path, monkeypatch):
    import shutil as shutil_module

    src = source_folder(tmp_path, ["a.png", "b.png", "c.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png", "b.png", "c.png"])})
    real_copy = shutil_module.copy2
    calls = []

    def failing_copy(a, b, *args, **kwargs):
        calls.append(a)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return real_copy(a, b, *args, **kwargs)

    monkeypatch.setattr("pipeline.importers.shutil.copy2", failing_copy)
    with pytest.raises(PanoError, match="No space left on device"):
        import_nerfstudio(t, tmp_path / "out")
    assert len(calls) == 2
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no temporary folder left either


def test_failure_keeps_an_existing_empty_out(tmp_path, monkeypatch):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    (tmp_path / "out").mkdir()
    def failing_copy(*args, **kwargs):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr("pipeline.importers.shutil.copy2", failing_copy)
    with pytest.raises(PanoError):
        import_nerfstudio(t, tmp_path / "out", test_every=0)
    assert (tmp_path / "out").is_dir() and not any((tmp_path / "out").iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "src"]


def test_empty_out_is_filled(tmp_path):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    (tmp_path / "out").mkdir()
    path = import_nerfstudio(t, tmp_path / "out", test_every=0)
    assert path == tmp_path / "out" / "scene.json" and path.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "src"]


def test_symlinked_empty_out_is_filled_through_the_link(tmp_path):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    (tmp_path / "real").mkdir()
    os.symlink(tmp_path / "real", tmp_path / "out")
    import_nerfstudio(t, tmp_path / "out", test_every=0)
    assert (tmp_path / "out").is_symlink() and (tmp_path / "real" / "scene.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "real", "src"]


def test_non_empty_out_is_refused(tmp_path, capsys):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    assert_refused(t, out, capsys, "out", "not empty", "choose a new or empty folder")
    assert (out / "precious.txt").read_text() == "keep me"


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    (tmp_path / "out").write_text("a file")
    assert_refused(t, tmp_path / "out", capsys, "out", "not a folder")
    assert (tmp_path / "out").read_text() == "a file"


@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_overlapping_source_is_refused(tmp_path, capsys, where):
    src = source_folder(tmp_path / "outer", ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    out = {"same": src, "inside": src / "scene", "contains": tmp_path / "outer"}[where]
    before = snapshot(tmp_path)
    assert_refused(t, out, capsys, "source folder", "transforms.json")
    assert snapshot(tmp_path) == before


# 3 and 4. View names: unique and safe stems, deterministically.


def test_duplicate_stems_get_unique_names(tmp_path):
    paths = ["a/frame.png", "b/frame.png", "frame.jpg", "frame_2.png", "c/Frame.png"]
    src = source_folder(tmp_path, paths)
    t = write_transforms(src, {"frames": frames_for(paths)})
    import_nerfstudio(t, tmp_path / "out", test_every=0)
    scene = load_scene(tmp_path / "out", check_images=False)
    names = [v.name for v in scene.views]
    assert names == ["frame", "frame_3", "frame_4", "frame_2", "Frame_5"]
    for v, rel in zip(scene.views, paths):  # every image copied, none overwritten
        assert (tmp_path / "out" / v.image).read_bytes() == b"image " + rel.encode()
    assert len({v.image.casefold() for v in scene.views}) == len(paths)


def test_unique_names_is_deterministic():
    assert unique_names(["x", "x", "x_2", "y"]) == ["x", "x_3", "x_2", "y"]
    assert unique_names(["x", "x", "x"]) == ["x", "x_2", "x_3"]


def test_unsafe_stems_are_sanitised(tmp_path):
    paths = [".hidden.png", "-rf.png", "a|b*c?.png", "...png", "tab\tname.png", "ok.PNG"]
    src = source_folder(tmp_path, paths)
    t = write_transforms(src, {"frames": frames_for(paths)})
    import_nerfstudio(t, tmp_path / "out", test_every=0)
    scene = json.loads((tmp_path / "out" / "scene.json").read_text())
    names = [v["name"] for v in scene["views"]]
    assert names == ["hidden", "rf", "a_b_c_", "view", "tab_name", "ok"]
    assert [v["image"] for v in scene["views"]][-1] == "images/ok.PNG"
    for n in names:
        safe_stem(n)
    for v, rel in zip(scene["views"], paths):
        assert (tmp_path / "out" / v["image"]).read_bytes() == b"image " + rel.encode()


@pytest.mark.parametrize(
    "name", ["..", ".", "-", " x ", "a/b", "\x00", "\u3000x\u00a0.", "é" * 200, "x" * 300, "CON", "a\udcff"]
)
def test_sanitize_stem_always_gives_a_safe_stem(name):
    assert safe_stem(sanitize_stem(name)) == sanitize_stem(name) == sanitize_stem(name)


def test_unsafe_out_name_gives_a_safe_scene_name(tmp_path):
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png"])})
    import_nerfstudio(t, tmp_path / ".scene", test_every=0)
    assert json.loads((tmp_path / ".scene" / "scene.json").read_text())["name"] == "scene"


# 5. Malformed transforms.json: one line naming the file and the field, exit 2, nothing written.

GOOD = frames_for(["a.png"])


def bad_matrix(m):
    return {"frames": [*GOOD, *GOOD, *GOOD, {"file_path": "a.png", "transform_matrix": m}]}


def scaled():
    m = np.eye(4)
    m[:3, :3] *= 2
    return m.tolist()


def mirrored():
    return np.diag([1.0, 1.0, -1.0, 1.0]).tolist()


def one(**frame) -> dict:
    return {"frames": [frame]}


def raw_matrix(first_row: str) -> str:
    """transforms.json text whose matrix's first row is written verbatim (NaN, 1e999, ...)."""
    return ('{"frames": [{"file_path": "a.png", "transform_matrix": [[' + first_row
            + '], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}')


TM = "frames.3.transform_matrix"
MALFORMED = {
    "top level a list": ([1, 2], "top level must be a JSON object"),
    "top level a string": ('"frames"', "top level must be a JSON object"),
    "frames missing": ({}, "frames: must be a non-empty list"),
    "frames an object": ({"frames": {"0": GOOD[0]}}, "frames: must be a non-empty list"),
    "frames empty": ({"frames": []}, "frames: must be a non-empty list"),
    "frame a string": ({"frames": [*GOOD, "a.png"]}, "frames.1: must be an object"),
    "file_path missing": ({"frames": [*GOOD, {"transform_matrix": IDENTITY}]}, "frames.1.file_path: missing"),
    "file_path a number": (one(file_path=3, transform_matrix=IDENTITY), "frames.0.file_path: must be a str"),
    "file_path empty": (one(file_path="", transform_matrix=IDENTITY), "frames.0.file_path"),
    "file_path NUL": (one(file_path="a.png\x00", transform_matrix=IDENTITY), "frames.0.file_path"),
    "matrix missing": ({"frames": [*GOOD, {"file_path": "a.png"}]}, "frames.1.transform_matrix: missing"),
    "matrix a number": (bad_matrix(1.0), f"{TM}: must be a 4x4"),
    "matrix flat": (
        bad_matrix(list(range(16))), f"{TM}: must be a 4x4 (or 3x4) list of rows of numbers, got 16 rows"
    ),
    "matrix of numbers": (bad_matrix([1, 2, 3, 4]), f"{TM}.0: each row must hold 4 numbers, got int"),
    "matrix 2 rows": (bad_matrix(IDENTITY[:2]), f"{TM}: must be a 4x4"),
    "matrix 5 rows": (bad_matrix([*IDENTITY, [0, 0, 0, 1]]), f"{TM}: must be a 4x4"),
    "matrix short row": (bad_matrix([[1, 0, 0], *IDENTITY[1:]]), f"{TM}.0: each row must hold 4"),
    "matrix string entry": (bad_matrix([[1, 0, 0, "x"], *IDENTITY[1:]]), f"{TM}.0.3: must be a number"),
    "matrix bool entry": (bad_matrix([[True, 0, 0, 0], *IDENTITY[1:]]), f"{TM}.0.0: must be a number"),
    "matrix null entry": (bad_matrix([[None, 0, 0, 0], *IDENTITY[1:]]), f"{TM}.0.0: must be a number"),
    "matrix NaN": (raw_matrix("NaN, 0, 0, 0"), "frames.0.transform_matrix.0.0: must be finite"),
    "matrix Infinity": (raw_matrix("1, 0, 0, 1e999"), "frames.0.transform_matrix.0.3: must be finite"),
    "matrix huge int": (raw_matrix("1, 0, 0, " + "9" * 400), "frames.0.transform_matrix.0.3: must be finite"),
    "matrix bad last row": (bad_matrix([*IDENTITY[:3], [0, 0, 1, 1]]), f"{TM}.3: last row must be"),
    "matrix scaled": (bad_matrix(scaled()), f"{TM}: not a rigid transform"),
    "matrix mirrored": (bad_matrix(mirrored()), f"{TM}: not a rigid transform"),
    # Caught by the scene schema's pose check (schemas/scene.py MAX_TRANSLATION), named as the frame's field.
    "matrix far away": (bad_matrix([[1, 0, 0, 1e9], *IDENTITY[1:]]), f"{TM}: translation"),
    "camera model": ({"camera_model": "PINHOLE", "frames": GOOD}, "frames.0: camera_model must be EQUIRECT"),
    "test_filenames a string": ({"frames": GOOD, "test_filenames": "a.png"}, "test_filenames: must be"),
    "all test": ({"frames": GOOD, "test_filenames": ["a.png"]}, "no train views"),
    "invalid JSON": ('{"frames": [', "invalid JSON at line 1"),
    "deeply nested": ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_transforms_is_one_line(tmp_path, capsys, case):
    meta, expected = MALFORMED[case]
    src = source_folder(tmp_path, ["a.png"])
    t = write_transforms(src, meta)
    assert_refused(t, tmp_path / "out", capsys, "transforms.json", expected)
    assert not (tmp_path / "out").exists()


def test_non_utf8_transforms_is_one_line(tmp_path, capsys):
    src = source_folder(tmp_path, ["a.png"])
    t = src / "transforms.json"
    t.write_bytes(b'{"frames": [{"file_path": "\xff\xfe.png"}]}')
    assert_refused(t, tmp_path / "out", capsys, "transforms.json", "UTF-8")


def test_transforms_is_a_folder(tmp_path, capsys):
    (tmp_path / "transforms.json").mkdir()
    assert_refused(tmp_path / "transforms.json", tmp_path / "out", capsys, "transforms.json", "is a folder")


def test_image_that_is_a_folder_is_refused(tmp_path, capsys):
    src = source_folder(tmp_path, ["a.png"])
    (src / "dir.png").mkdir()
    t = write_transforms(src, {"frames": frames_for(["a.png", "dir.png"])})
    assert_refused(t, tmp_path / "out", capsys, "dir.png", "not a regular file", "frames.1.file_path")


# 6. Options.


@pytest.mark.parametrize(
    "args, expected",
    [
        (("--test-every", "-1"), "--test-every"),
        (("--test-every", "1"), "no train views"),
        (("--world-up", "z"), "--world-up"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, args, expected):
    src = source_folder(tmp_path, ["a.png", "b.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png", "b.png"])})
    assert_refused(t, tmp_path / "out", capsys, expected, args=args)


def test_cli_import_succeeds(tmp_path, capsys):
    src = source_folder(tmp_path, ["a.png", "b.png"])
    t = write_transforms(src, {"frames": frames_for(["a.png", "b.png"])})
    code, err = run_cli(["import-nerfstudio", str(t), str(tmp_path / "out"), "--test-every", "2"], capsys)
    assert code == 0, err
    scene = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert [(v["name"], v["split"]) for v in scene["views"]] == [("a", "train"), ("b", "test")]
