"""The scene folders a batch command names."""

from __future__ import annotations

from pathlib import Path

from runfs.errors import PanoError

MANIFEST = "scene.json"


def expand_scenes(args: list[Path]) -> list[Path]:
    """Scene folders, in the order given: each argument is a scene folder (it holds scene.json)
    or a folder of scene folders (its children holding scene.json, by name). Shell globs arrive
    expanded. Duplicates are dropped; a path that is neither is kept, so that it fails alone with
    its own message."""
    scenes: list[Path] = []
    seen: set[Path] = set()
    for arg in args:
        arg = Path(arg)
        found = [arg]
        if arg.is_dir() and not (arg / MANIFEST).exists():
            children = sorted(c for c in arg.iterdir() if c.is_dir() and (c / MANIFEST).is_file())
            if children:
                found = children
        for scene in found:
            key = scene.resolve() if scene.exists() else scene.absolute()
            if key not in seen:
                seen.add(key)
                scenes.append(scene)
    return scenes


def is_batch(args: list[Path]) -> bool:
    """Whether a command line names a batch (several scenes, or a folder of scenes) rather than
    one scene; a batch's --out is the root of one run folder per scene."""
    return len(args) > 1 or any(Path(a).is_dir() and not (Path(a) / MANIFEST).exists() for a in args)


def run_folders(scenes: list[Path], names: dict[Path, str], out_root: Path) -> dict[Path, Path]:
    """OUT/<scene-name>/ per scene. Two scenes of one name would share a run folder: refused."""
    folders: dict[Path, Path] = {}
    by_name: dict[str, Path] = {}
    for scene in scenes:
        name = names.get(scene, scene.name)
        if name in by_name:
            raise PanoError(scene, f"has the scene name {name!r}, like {by_name[name]}; their run folders "
                                   f"would be one ({out_root / name}): rename one scene (scene.json \"name\")")
        by_name[name] = scene
        folders[scene] = Path(out_root) / name
    return folders
