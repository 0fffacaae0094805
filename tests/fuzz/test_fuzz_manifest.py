"""Fuzz scene.json: structure, values, names, paths and encodings (the bad-input contract)."""

from __future__ import annotations

import json
import shutil

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from fuzz_helpers import (
    HOSTILE_NAMES,
    HOSTILE_PATHS,
    NUMBERS,
    SCENE_VIEWS,
    deep,
    fuzz_settings,
    json_dumps_deep,
    run_args,
    run_example,
    sandbox,
)

VIEW_KEYS = ["name", "image", "pose", "split", "camera_height", "layout", "depth", "gt_depth"]
TOP_KEYS = ["name", "views", "floor_plan"]
PATH_KEYS = ["image", "layout", "depth", "gt_depth"]

numbers = st.one_of(st.sampled_from(NUMBERS), st.floats(), st.integers())
junk = st.one_of(
    st.none(),
    st.booleans(),
    numbers,
    st.text(max_size=12),
    st.sampled_from(HOSTILE_NAMES),
    st.sampled_from(HOSTILE_PATHS),
    st.lists(numbers, max_size=5),
    st.lists(st.lists(numbers, min_size=4, max_size=4), min_size=4, max_size=4),
    st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
    st.sampled_from([{"$ref": "#"}, [[0] * 4] * 3, "train", "test", "TRAIN", ""]),
)
view_index = st.integers(0, len(SCENE_VIEWS) - 1)

ops = st.one_of(
    st.tuples(st.just("del_top"), st.sampled_from(TOP_KEYS)),
    st.tuples(st.just("set_top"), st.sampled_from(TOP_KEYS + ["extra"]), junk),
    st.tuples(st.just("del_view_key"), view_index, st.sampled_from(VIEW_KEYS)),
    st.tuples(st.just("set_view_key"), view_index, st.sampled_from(VIEW_KEYS + ["extra"]), junk),
    st.tuples(st.just("view_name"), view_index, st.sampled_from(HOSTILE_NAMES)),
    st.tuples(st.just("scene_name"), st.sampled_from(HOSTILE_NAMES)),
    st.tuples(st.just("view_path"), view_index, st.sampled_from(PATH_KEYS), st.sampled_from(HOSTILE_PATHS)),
    st.tuples(st.just("floor_plan"), st.sampled_from(HOSTILE_PATHS)),
    st.tuples(st.just("pose_entry"), view_index, st.integers(0, 3), st.integers(0, 3), numbers),
    st.tuples(st.just("translation"), view_index, st.sampled_from([1e308, -1e308, 1e5 + 1, 1e5, 1e300, 1e15])),
    st.tuples(st.just("camera_height"), view_index, numbers),
    st.tuples(st.just("split"), view_index, st.sampled_from(["test", "train", "TRAIN", "", None, 1, ["train"]])),
    st.tuples(st.just("dup_view"), view_index),
    st.tuples(st.just("drop_view"), view_index),
    st.tuples(st.just("many_views"), st.sampled_from([0, 60])),
)

encodings = st.one_of(
    st.just(("json",)),
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("non_utf8"), st.floats(0.0, 1.0), st.sampled_from([b"\xff", b"\xc3(", b"\xed\xa0\x80", b"\x80", b"\xfe\xff"])),
    st.just(("bom",)),
    st.just(("utf16",)),
    st.tuples(st.just("deep"), st.sampled_from([64, 1000, 100_000])),
    st.tuples(st.just("raw"), st.sampled_from(["", "null", "[]", "{}", "0", '"scene"', "{\"views\": []}",
                                               "{\"views\": [null]}", "{\"views\": {}}", "NaN", "[" * 50,
                                               "{\"views\": [{}]}", "{\"views\": \"../x\"}"])),
    st.tuples(st.just("raw_bytes"), st.binary(max_size=40)),
)

commands = st.sampled_from(["run-all", "status", "run-stage-layout", "clean"])


def apply_op(data, op) -> None:
    """Apply one mutation to the parsed manifest (ops on parts already gone are no-ops)."""
    kind = op[0]
    views = data.get("views") if isinstance(data, dict) else None
    view = None
    if kind not in ("del_top", "set_top", "scene_name", "floor_plan", "many_views"):
        if not isinstance(views, list) or not views:
            return
        view = views[op[1] % len(views)]
        if not isinstance(view, dict):
            return
    if kind == "del_top":
        data.pop(op[1], None)
    elif kind == "set_top":
        data[op[1]] = op[2]
    elif kind == "del_view_key":
        view.pop(op[2], None)
    elif kind == "set_view_key":
        view[op[2]] = op[3]
    elif kind == "view_name":
        view["name"] = op[2]
    elif kind == "scene_name":
        data["name"] = op[1]
    elif kind == "view_path":
        view[op[2]] = op[3]
    elif kind == "floor_plan":
        data["floor_plan"] = op[1]
    elif kind == "pose_entry":
        try:
            view["pose"][op[2]][op[3]] = op[4]
        except (KeyError, IndexError, TypeError):
            pass
    elif kind == "translation":
        try:
            view["pose"][0][3] = op[2]
        except (KeyError, IndexError, TypeError):
            pass
    elif kind == "camera_height":
        view["camera_height"] = op[2]
    elif kind == "split":
        view["split"] = op[2]
    elif kind == "dup_view":
        views.append(dict(view))
    elif kind == "drop_view":
        views.remove(view)
    elif kind == "many_views":
        if isinstance(views, list) and views:
            base = views[0]
            data["views"] = [dict(base, name=f"v{i}") for i in range(op[1])]


def encode(data, encoding) -> bytes:
    kind = encoding[0]
    if kind == "deep":
        nested = deep(encoding[1])
        if isinstance(data, dict) and isinstance(data.get("views"), list) and data["views"]:
            data["views"][0] = {"nested": "X"} if isinstance(data["views"][0], dict) else data["views"][0]
            text = json.dumps(data).replace('"X"', json_dumps_deep(nested), 1)
        else:
            text = json_dumps_deep(nested)
        return text.encode()
    if kind == "raw":
        return encoding[1].encode()
    if kind == "raw_bytes":
        return encoding[1]
    text = json.dumps(data, indent=1, ensure_ascii=False)  # NaN / Infinity tokens where asked for
    raw = text.encode("utf-8", "surrogatepass")
    if kind == "truncate":
        return raw[: int(len(raw) * encoding[1])]
    if kind == "non_utf8":
        at = int(len(raw) * encoding[1])
        return raw[:at] + encoding[2] + raw[at:]
    if kind == "bom":
        return b"\xef\xbb\xbf" + raw
    if kind == "utf16":
        return text.encode("utf-16")
    return raw


@given(
    mutation=st.tuples(st.lists(ops, min_size=1, max_size=3), encodings, commands),
)
@example(mutation=([("view_name", 0, "../../sentinel/pwn")], ("json",), "run-all"))
@example(mutation=([("view_name", 1, "<SENTINEL>/pwn")], ("json",), "run-all"))
@example(mutation=([("view_name", 0, "a/b")], ("json",), "run-stage-layout"))
@example(mutation=([("view_name", 2, "x\x00y")], ("json",), "run-all"))
@example(mutation=([("view_name", 0, "[/b]")], ("json",), "status"))
@example(mutation=([("view_name", 0, "x" * 300)], ("json",), "run-all"))
@example(mutation=([("scene_name", "../x")], ("json",), "clean"))
@example(mutation=([("view_path", 0, "image", "../sentinel/img.png")], ("json",), "run-all"))
@example(mutation=([("view_path", 1, "layout", "<SENTINEL>/layout.json")], ("json",), "run-all"))
@example(mutation=([("view_path", 2, "depth", "images/../../sentinel/img.png")], ("json",), "run-all"))
@example(mutation=([("translation", 0, 1e308)], ("json",), "run-all"))
@example(mutation=([("pose_entry", 1, 0, 0, float("nan"))], ("json",), "run-all"))
@example(mutation=([("split", 0, "test")], ("non_utf8", 0.5, b"\xff"), "run-all"))
@example(mutation=([("split", 0, "test")], ("deep", 100_000), "status"))
@example(mutation=([("split", 0, "test")], ("truncate", 0.5), "run-all"))
@fuzz_settings(max_examples=30)
def test_manifest_mutations(mutation, fuzz_base, tmp_path, capfd):
    ops_, encoding, command = mutation
    with sandbox(fuzz_base, tmp_path) as sb:
        data = sb.manifest()
        for op in ops_:
            apply_op(data, op)
        data = sb.expand(data)
        (sb.scene / "scene.json").write_bytes(encode(data, encoding))
        run_example(sb, run_args("layout", command), capfd, mutation, "manifest")


#: (a file the scene names, replaced by a symlink to this target)
SYMLINK_CASES = [
    ("images/train_00.png", "<SENTINEL>/img.png"),
    ("images/train_00.png", "../../sentinel/img.png"),
    ("images/test_00.png", "<SENTINEL>/img.png"),
    ("layout/train_01.json", "<SENTINEL>/layout.json"),
    ("depth/train_02.png", "<SENTINEL>/depth.png"),
    ("gt/depth/test_00.npy", "<SENTINEL>/depth.npy"),
    ("gt/floor_plan.json", "<SENTINEL>/secret.txt"),
    ("images", "<SENTINEL>/images"),
    ("layout", "<SENTINEL>"),
    ("images/train_00.png", "train_00.png"),  # a loop
    ("images/train_00.png", "nowhere.png"),  # dangling
    ("images/train_00.png", "/dev/null"),
    ("images/train_00.png", "../images/train_01.png"),  # inside the scene: fine
    ("scene.json", "<SENTINEL>/scene.json"),
]


@pytest.mark.parametrize("command", ["run-all", "status"])
@pytest.mark.parametrize("case", SYMLINK_CASES, ids=[f"{a}->{b}" for a, b in SYMLINK_CASES])
def test_symlinks_out_of_the_scene(case, command, fuzz_base, tmp_path, capfd):
    """A file the scene names is a symlink: pointing outside the scene it must be refused."""
    rel, target = case
    with sandbox(fuzz_base, tmp_path) as sb:
        link = sb.scene / rel
        if link.is_dir() and not link.is_symlink():
            shutil.rmtree(link)
        else:
            link.unlink()
        link.symlink_to(sb.expand(target))
        run_example(sb, run_args("align", command), capfd, case, "symlinks")
