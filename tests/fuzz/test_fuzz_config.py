"""Fuzz configuration: --config files (YAML/JSON) and --set overrides, and hostile --out folders."""

from __future__ import annotations

import shutil

import pytest
import yaml
from hypothesis import example, given
from hypothesis import strategies as st

from fuzz_helpers import BASE_SET, fuzz_settings, run_args, run_example, sandbox
from pipeline.registry import build_registry

REGISTRY = build_registry()
STAGE_PARAMS = {name: sorted(spec.params.model_fields) for name, spec in REGISTRY.items()}
NAN, INF = float("nan"), float("inf")

# (No NUL characters on the command line: a real argv cannot hold them.)

#: Values for parameters. No large counts: a valid `align.ransac_iterations: 10**9` is a slow run,
#: not bad input, and would only make the suite slow.
param_values = st.sampled_from([
    0, -1, 1, 2, 1e-9, 0.5, 0.999, 1.5, NAN, INF, -INF, True, False, None, "", "x", "1", "auto", "cuda",
    [], {}, [1, 2], [8, 16], [0, 0], [1e-9, 1e-9, 1e-9], {"a": 1}, ["wall"], ["nope"], ["CUDAExecutionProvider"],
    ["../x"], "<SENTINEL>/model.onnx", "<SENTINEL>/secret.txt", "<SENTINEL>", "../sentinel/model.onnx",
    "images/train_00.png", "<SCENE>/scene.json", "/dev/null", "nope.onnx", "~/nope.onnx", "[/b]", "\x00",
    "x" * 300, "../../../../../../etc/passwd",
])
stage_names = st.sampled_from(sorted(REGISTRY) + ["nope", "", "../x", "Layout", "all", "__class__"])


@st.composite
def stage_param(draw):
    stage = draw(stage_names)
    params = STAGE_PARAMS.get(stage, []) + ["nope", "", "model_config", "__dict__", "MODEL"]
    return stage, draw(st.sampled_from(params))


config_dicts = st.dictionaries(
    stage_names,
    st.one_of(st.dictionaries(st.text(max_size=3), param_values, max_size=2), param_values),
    max_size=3,
)


@st.composite
def typed_config(draw):
    """{stage: {param: value}} with real stage and parameter names (values still hostile)."""
    out: dict = {}
    for stage, param in draw(st.lists(stage_param(), min_size=1, max_size=3)):
        out.setdefault(stage, {})[param] = draw(param_values)
    return out


RAW_CONFIGS = [
    "train: [1, 2", "{", "- a\n- b", "42", "null", "", "\t", "layout: 1", "layout: [model]",
    "layout: {model: !!python/object/apply:os.system ['touch <SENTINEL>/pwned']}",
    "!!python/object/apply:os.system ['touch <SENTINEL>/pwned']", "layout: &a {tta: *a}", "&a [*a]",
    "a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
    "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
    "layout: {threads: [*d, *d, *d, *d, *d, *d, *d, *d, *d]}",
    "layout:\n  model: x\nlayout:\n  model: y", "? [a, b]\n: 1", "{[1]: {}}", "1: {}", "null: {}",
    "layout: {1: 2}", "layout: {threads: 0x10}", "layout: {threads: 1_0}", "layout: {peak_r: .inf}",
    "layout: {peak_r: .nan}", "sampling: {density: 1.0e+400}", "%YAML 9.9\n---\n{}", "--- {}\n--- {}",
    "[/b]: {}", "\ufeff{}", "layout: {mode: \"\\x00\"}", '{"layout": {"tta": true}}',
]

config_files = st.one_of(
    st.tuples(st.just("yaml"), typed_config()),
    st.tuples(st.just("yaml"), config_dicts),
    st.tuples(st.just("raw"), st.sampled_from(RAW_CONFIGS)),
    st.tuples(st.just("bytes"), st.sampled_from([b"\xff\xfe", b"layout: {mode: \xc3(}", b"\x00\x01", b"\xef\xbb"])),
    st.tuples(st.just("deep"), st.sampled_from([100, 100_000])),
    st.sampled_from([("dir",), ("missing",), ("sentinel",), ("scene_json",)]),
)

SET_VALUES = [
    "[1, 2", "{", "!!python/name:os.system", "!!python/object/apply:os.system [true]", "&a [*a]", "1e999",
    "1.0e+999", ".nan", "-.inf", "-1", "0", "null", "~", "'", '"', "\t", "x" * 5000, "[" * 5000, "0x10",
    "yes", "<SENTINEL>/model.onnx", "../sentinel/model.onnx", "<SENTINEL>", "", " ", "[/b]", "{a: 1}",
    "[8, 16]", "true", "2", "0.5", "%", "@x", "`x`", "a: b: c", "- x",
]
set_items = st.one_of(
    st.builds(lambda sp, v: f"{sp[0]}.{sp[1]}={v}", stage_param(), st.sampled_from(SET_VALUES)),
    st.sampled_from(["oops", "=1", ".=1", "a.=1", ".b=1", "layout.model", "layout..model=1",
                     "layout.model=a=b", "layout.model.x=1", " layout.tta=true", "layout.tta =true", "é.x=1"]),
)


def write_config(sb, spec):
    """The --config argument for `spec` (a path string), or None for no --config."""
    kind = spec[0]
    path = sb.root / "config.yaml"
    if kind == "yaml":
        try:
            text = yaml.safe_dump(sb.expand(spec[1]), allow_unicode=True)
        except yaml.YAMLError:
            text = repr(spec[1])
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
    elif kind == "raw":
        path.write_text(sb.expand(spec[1]), encoding="utf-8")
    elif kind == "bytes":
        path.write_bytes(spec[1])
    elif kind == "deep":
        path.write_text("layout: {threads: " + "[" * spec[1] + "]" * spec[1] + "}")
    elif kind == "dir":
        path.mkdir()
    elif kind == "missing":
        pass
    elif kind == "sentinel":
        return "<SENTINEL>/secret.txt"
    elif kind == "scene_json":
        return "<SCENE>/scene.json"
    return str(path)


@given(
    config=st.one_of(st.none(), config_files),
    sets=st.lists(set_items, max_size=3),
    until=st.sampled_from(["layout", "depth", "union", "align", "status"]),
)
@example(config=("raw", "layout: {model: !!python/object/apply:os.system ['touch <SENTINEL>/pwned']}"),
         sets=[], until="layout")
@example(config=("raw", "layout: &a {tta: *a}"), sets=[], until="layout")
@example(config=("bytes", b"layout: {mode: \xc3(}"), sets=[], until="layout")
@example(config=("deep", 100_000), sets=[], until="status")
@example(config=None, sets=["layout.model=<SENTINEL>/model.onnx"], until="layout")
@example(config=None, sets=["depth.model=<SENTINEL>/model.onnx"], until="depth")
@example(config=None, sets=["layout.tta=[1, 2"], until="layout")
@example(config=None, sets=["sampling.seed=-1"], until="align")
@example(config=None, sets=["align.voxel_size=.inf"], until="align")
@fuzz_settings(max_examples=30)
def test_config_mutations(config, sets, until, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb:
        args = run_args("status" if until == "status" else until, "status" if until == "status" else "run-all")
        if config is not None:
            args += ["--config", write_config(sb, config)]
        for item in sets:
            args += [f"--set={item}"]
        run_example(sb, args, capfd, (config, sets, until), "config")


# ----------------------------------------------------------------------------- --out
#: Run folders that are not this scene's: the scene itself, inside it, around it, files and
#: folders pano-pipe did not make. Each must be refused, with nothing written anywhere.
HOSTILE_OUTS = [
    "<SCENE>", "<SCENE>/images", "<SCENE>/new", "<ROOT>", "<SENTINEL>", "<SENTINEL>/secret.txt",
    "<SENTINEL>/images", "../scene", "<RUN>/../scene", "<SCENE>/scene.json", "<RUN>/layout",
    "<RUN>/run_log.jsonl", "<CWD>/../sentinel/../scene/images",
]


@pytest.mark.parametrize("command", ["run", "clean"])
@pytest.mark.parametrize("out", HOSTILE_OUTS)
def test_hostile_out_folder(out, command, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb:
        if command == "run":
            args = ["run", "all", "<SCENE>", "--out", out, "--until", "layout", *BASE_SET]
        else:
            args = ["clean", "<SCENE>", "--out", out, "--yes"]
        run_example(sb, args, capfd, (out, command), "out")


#: The run folder holds symlinks pointing out of it: the pipeline must not write through them.
RUN_LINKS = [
    ("run_log.jsonl", "<SENTINEL>/run_log.jsonl"),
    (".lock", "<SENTINEL>/secret.txt"),
    (".pano-pipe-run", "<SENTINEL>/secret.txt"),
    ("layout", "<SENTINEL>"),
    ("layout/artifact.json", "<SENTINEL>/secret.txt"),
    ("depth/depth", "<SENTINEL>"),
    (".scratch", "<SENTINEL>"),
]


@pytest.mark.parametrize("command", ["run", "clean"])
@pytest.mark.parametrize("case", RUN_LINKS, ids=[c[0] for c in RUN_LINKS])
def test_run_folder_symlinks(case, command, fuzz_base, tmp_path, capfd):
    rel, target = case
    with sandbox(fuzz_base, tmp_path) as sb:
        link = sb.run / rel
        if link.is_dir() and not link.is_symlink():
            shutil.rmtree(link)
        else:
            link.unlink(missing_ok=True)
        link.symlink_to(sb.expand(target))
        # the scene changed too, so the layout stage really reruns and writes
        data = sb.manifest()
        data["views"][0]["camera_height"] = 1.7
        sb.write_manifest(data)
        if command == "run":
            args = ["run", "all", "<SCENE>", "--out", "<RUN>", "--until", "depth", *BASE_SET]
        else:
            args = ["clean", "<SCENE>", "--out", "<RUN>", "--yes"]
        run_example(sb, args, capfd, (case, command), "run-folder-links")
