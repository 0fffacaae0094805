"""Stage settings from their three sources (DESIGN.md): the scene's `pano-pipe.yaml`, `--config FILE`
and `--set STAGE.PARAM=VALUE`, each parameter taken from the last that sets it.

The scene's file comes with the scene, from elsewhere, so it is held to the scene's rule
(docs/security.md): it is a regular file inside the scene folder, not a link, and a setting in it
that names a file (a model, LPIPS weights: `file_settings`) names one inside the scene folder, or a
known model by name. `--config` and `--set` are the user's own: they may name any file.
"""

from __future__ import annotations

import os
from pathlib import Path

from runfs.errors import PanoError
from runfs.yamlfile import parse_yaml, read_yaml, yaml_scalar

#: The scene's own stage parameters (DESIGN.md): below --config and --set.
SCENE_CONFIG = "pano-pipe.yaml"

#: What a scene folder made from captured panoramas (`new`, `import-nerfstudio`, `import-colmap`)
#: starts with in its pano-pipe.yaml, {stage: {param: (value, why)}}; measured on real and simulated
#: sparse captures in docs/training.md ("Settings for real captures").
REAL_CAPTURE_SETTINGS: dict[str, dict[str, tuple[object, str]]] = {
    "train": {
        "appearance": (True, "learn each panorama's exposure and white balance"),
        "random_turn_interp": ("bilinear", "low-pass the turned panoramas, as the crops' resampling does"),
    },
}


def real_capture_settings_text(command: str) -> str:
    """REAL_CAPTURE_SETTINGS as the pano-pipe.yaml `command` writes, each setting with its reason."""
    lines = [f"# Settings for captured panoramas, written by `pano-pipe {command}` (docs/training.md,",
             '# "Settings for real captures"). --config and --set override them; edit or delete freely.']
    for stage, params in REAL_CAPTURE_SETTINGS.items():
        lines.append(f"{stage}:")
        width = max(len(f"{param}: {yaml_scalar(value)}") for param, (value, _) in params.items())
        lines += [f"  {f'{param}: {yaml_scalar(value)}':<{width}}  # {why}" for param, (value, why) in params.items()]
    return "\n".join(lines) + "\n"


def load_config(path: Path | None, overrides: list[str] | None) -> tuple[dict[str, dict], str]:
    """Stage parameters from a YAML/JSON file plus `--set stage.param=value` overrides."""
    config: dict[str, dict] = {}
    source = "--set"
    if path is not None:
        source = str(path)
        if not os.path.lexists(path):
            raise PanoError(path, "config file does not exist")
        loaded = read_yaml(path, "settings file") or {}
        if not isinstance(loaded, dict) or not all(isinstance(v, dict) for v in loaded.values()):
            raise PanoError(path, "expected a mapping {stage: {param: value}}")
        config = {str(k): dict(v) for k, v in loaded.items()}
    for item in overrides or []:
        lhs, sep, value = item.partition("=")
        stage, dot, param = lhs.partition(".")
        if not sep or not dot or not stage or not param:
            raise PanoError("--set", f"{item!r} is not STAGE.PARAM=VALUE")
        try:
            config.setdefault(stage, {})[param] = _override_value(stage, param, value)
        except PanoError as e:
            raise PanoError("--set", f"{item!r}: the value is {e.problem}") from None
    return config, source


def _override_value(stage: str, param: str, text: str):
    """A --set value, typed by the parameter's schema: the text itself where the parameter takes
    it ('360' for a projection that is '360' or 'cubemap'; '5' for a number), else the text
    parsed as YAML (lists, null)."""
    from pydantic import TypeAdapter, ValidationError

    from pipeline.registry import build_registry

    spec = build_registry().get(stage)
    field = spec.params.model_fields.get(param) if spec is not None else None
    if field is not None:
        try:
            value = TypeAdapter(field.annotation).validate_python(text)
            return value if isinstance(value, bool | int | float | str) else text
        except (ValidationError, TypeError, ValueError):
            pass
    return parse_yaml(text, "--set")


def file_settings(params_model) -> set[str]:
    """The parameters of a stage whose value names a file: those marked `names_file` in their
    Field's json_schema_extra, and any typed as a Path."""
    from schemas.stage_params import field_extra

    return {name for name, field in params_model.model_fields.items()
            if field_extra(field).get("names_file") or "Path" in str(field.annotation)}


def _scene_file_value(scene_root: Path, own: Path, stage: str, param: str, value):
    """A file setting from the scene's own file: a known model name (or none) as it is; a path
    only inside the scene folder, made absolute so nothing looks for it anywhere else."""
    from models.registry import known_models
    from runfs.paths import relative_problem, scene_file, shorten

    if not isinstance(value, str) or value.strip().lower() == "none" or value in known_models():
        return value  # not a path: the stage's own validation judges it
    problem = relative_problem(value, named_in=SCENE_CONFIG) or (
        "names the home folder ('~')" if value.startswith("~") else None)
    if problem:
        raise PanoError(own, f"{stage}.{param}: {shorten(value)} {problem}; a scene's settings may name only "
                             "files inside the scene folder (give others with --set or --config)")
    return str(scene_file(scene_root, value, named_by=f"{SCENE_CONFIG} {stage}.{param}").resolve())


def read_scene_settings(scene_root: Path) -> dict[str, dict] | None:
    """The scene's pano-pipe.yaml, checked (see the module doc); None when the scene has none."""
    from pipeline.registry import build_registry

    own = Path(scene_root) / SCENE_CONFIG
    if own.is_symlink():
        raise PanoError(own, "is a symbolic link; a scene's settings file must be a file inside the scene "
                             "folder (copy it there), as nothing a scene names may lie outside it")
    if not os.path.lexists(own):
        return None
    if not own.is_file():
        raise PanoError(own, "is not a regular file (a folder?); remove it or make it a settings file")
    settings, _ = load_config(own, None)
    registry = build_registry()
    for stage, params in settings.items():
        spec = registry.get(stage)
        for param in file_settings(spec.params) & set(params) if spec is not None else ():
            params[param] = _scene_file_value(Path(scene_root), own, stage, param, params[param])
    return settings


def scene_config(scene_dir: Path, config_file: Path | None, overrides: list[str] | None) -> tuple[dict[str, dict], str]:
    """Stage parameters for a scene: its pano-pipe.yaml, then --config, then --set, each
    parameter taken from the last that sets it."""
    config, source = load_config(config_file, overrides)
    base = read_scene_settings(scene_dir)
    if base is None:
        return config, source
    own = Path(scene_dir) / SCENE_CONFIG
    for stage, params in config.items():
        base.setdefault(stage, {}).update(params)
    given = config_file is not None or bool(overrides)
    return base, (f"{own} < {source}" if given else str(own))


def make_engine(scene_dir: Path, out: Path | None, config_file: Path | None, overrides: list[str] | None):
    """The engine for a scene folder as every command sees it: the scene, its settings (its
    pano-pipe.yaml, --config, --set) and its run folder (default runs/<scene-name>/)."""
    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from runfs.paths import default_run_folder
    from schemas.scene_loader import load_scene

    scene = load_scene(scene_dir)
    config, source = scene_config(scene.root, config_file, overrides)
    out_dir = out if out is not None else default_run_folder(scene.name, scene.root)
    return Engine(scene, out_dir, build_registry(), config, config_source=source)
